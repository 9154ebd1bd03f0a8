"""The paper's reconstruction figures (matplotlib, Agg, no pyplot state).

- :func:`cross_arm_figure`: orthographic XY, XZ and YZ projections of both arms' clouds in the world
  frame (arm110 red, arm111 blue): the cross-arm alignment figure.
- :func:`partial_fused_figure`: (a) arm110's partial cloud, (b) arm111's, (c) the fused cloud, in the
  same 3-D view and limits.
- :func:`heldout_histogram`: the distribution of held-out point-to-mesh distances per arm, with the
  median and the 5 / 10 mm marks of the paper's table.

Large clouds are subsampled (deterministically) for drawing only. Files are written atomically; the
format follows the file suffix (png, pdf, svg).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from darp.colours import arm_colour
from darp.errors import EvaluationError
from darp.formats.atomic import atomic_path

MAX_DRAWN_POINTS = 60_000


def _subsample(points: np.ndarray, limit: int, seed: int) -> np.ndarray:
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if points.shape[0] <= limit:
        return points
    keep = np.sort(np.random.default_rng(seed).choice(points.shape[0], size=limit, replace=False))
    return points[keep]


def _save(fig: Figure, out: str | Path, dpi: int = 130) -> Path:
    out = Path(out)
    FigureCanvasAgg(fig)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, format=out.suffix.lstrip(".") or "png", dpi=dpi)
    return out


def _check_clouds(clouds: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    out = {}
    for name, pts in clouds.items():
        arr = np.asarray(pts)
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise EvaluationError(f"cloud {name!r} must be (N, 3), got {arr.shape}")
        out[name] = arr
    if not any(len(p) for p in out.values()):
        raise EvaluationError("nothing to draw: every cloud is empty")
    return out


def cross_arm_figure(clouds: Mapping[str, np.ndarray], out: str | Path, *, title: str = "",
                     max_points: int = MAX_DRAWN_POINTS, seed: int = 0) -> Path:
    """Orthographic XY / XZ / YZ projections (mm, world frame) of each arm's cloud, one colour per arm."""
    clouds = _check_clouds(clouds)
    drawn = {name: _subsample(p, max_points // max(len(clouds), 1), seed + i) * 1000.0
             for i, (name, p) in enumerate(clouds.items())}
    everything = np.concatenate([p for p in drawn.values() if len(p)])
    lo, hi = everything.min(axis=0), everything.max(axis=0)
    pad = 0.05 * float((hi - lo).max()) + 1.0
    fig = Figure(figsize=(15, 5.2))
    axes = fig.subplots(1, 3)
    # draw all arms' points in one shuffled batch so that no arm hides the other where they overlap
    colours = np.concatenate([np.repeat(np.array([arm_colour(name, k)]), len(p))
                              for k, (name, p) in enumerate(drawn.items())])
    order = np.random.default_rng(seed).permutation(everything.shape[0])
    for ax, (i, j), label in zip(axes, ((0, 1), (0, 2), (1, 2)), ("XY", "XZ", "YZ"), strict=True):
        ax.scatter(everything[order, i], everything[order, j], s=1.5, c=colours[order], alpha=0.6,
                   linewidths=0, rasterized=True)
        for k, name in enumerate(drawn):  # legend entries only
            ax.scatter([], [], s=12, c=arm_colour(name, k), label=f"{name} ({len(clouds[name]):,} pts)")
        ax.set_xlim(lo[i] - pad, hi[i] + pad)
        ax.set_ylim(lo[j] - pad, hi[j] + pad)
        ax.set_aspect("equal")
        ax.set_xlabel(f"world {'XYZ'[i]} [mm]")
        ax.set_ylabel(f"world {'XYZ'[j]} [mm]")
        ax.set_title(f"{label} projection")
        ax.grid(True, linewidth=0.3)
    axes[0].legend(loc="upper left", fontsize=8)
    fig.suptitle(title or "Cross-arm alignment in the shared world frame")
    fig.tight_layout()
    return _save(fig, out)


def partial_fused_figure(partial_a: np.ndarray, partial_b: np.ndarray, fused: np.ndarray, out: str | Path, *,
                         names: tuple[str, str] = ("arm110", "arm111"), fused_colours: np.ndarray | None = None,
                         title: str = "", elev_deg: float = 25.0, azim_deg: float = -60.0,
                         max_points: int = MAX_DRAWN_POINTS // 2, seed: int = 0) -> Path:
    """Three 3-D panels with equal limits: (a) arm A's partial cloud, (b) arm B's, (c) the fused cloud.

    The fused cloud is drawn in its RGB colours when given (N, 3 uint8), else coloured by height.
    """
    clouds = _check_clouds({names[0]: partial_a, names[1]: partial_b, "fused": fused})
    rng_keep = np.random.default_rng(seed)
    fused_pts = np.asarray(fused, np.float64)
    colours = None
    if len(fused_pts) > max_points:
        keep = np.sort(rng_keep.choice(len(fused_pts), size=max_points, replace=False))
        fused_pts = fused_pts[keep]
        if fused_colours is not None:
            colours = np.asarray(fused_colours)[keep]
    elif fused_colours is not None:
        colours = np.asarray(fused_colours)
    panels = [(_subsample(clouds[names[0]], max_points, seed) * 1000.0, arm_colour(names[0], 0)),
              (_subsample(clouds[names[1]], max_points, seed + 1) * 1000.0, arm_colour(names[1], 1)),
              (fused_pts * 1000.0, None)]
    everything = np.concatenate([p for p, _ in panels if len(p)])
    centre = 0.5 * (everything.min(axis=0) + everything.max(axis=0))
    half = 0.5 * float((everything.max(axis=0) - everything.min(axis=0)).max()) + 1.0
    fig = Figure(figsize=(15, 5.4))
    labels = (f"(a) {names[0]} partial", f"(b) {names[1]} partial", "(c) fused")
    for k, ((pts, colour), label) in enumerate(zip(panels, labels, strict=True)):
        ax = fig.add_subplot(1, 3, k + 1, projection="3d")
        if len(pts):
            if colour is not None:
                c: object = colour
            elif colours is not None:
                c = np.asarray(colours, np.float64)[:, :3] / 255.0
            else:
                c = pts[:, 2]
            ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=1.5, c=c, cmap=None if colour or colours is not None
                       else "viridis", linewidths=0, alpha=0.9, rasterized=True)
        for axis, set_lim in enumerate((ax.set_xlim, ax.set_ylim, ax.set_zlim)):
            set_lim(centre[axis] - half, centre[axis] + half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=elev_deg, azim=azim_deg)
        ax.set_xlabel("X [mm]")
        ax.set_ylabel("Y [mm]")
        ax.set_zlabel("Z [mm]")
        n = len(clouds[(names[0], names[1], "fused")[k]])
        ax.set_title(f"{label} ({n:,} pts)")
    fig.suptitle(title or "Complementary partial clouds and their calibrated fusion")
    fig.tight_layout(rect=(0.0, 0.0, 1.0, 0.93))
    return _save(fig, out)


def heldout_histogram(distances: Mapping[str, np.ndarray], out: str | Path, *, title: str = "",
                      max_mm: float | None = None, bins: int = 120) -> Path:
    """Histogram of held-out point-to-mesh distances (mm) per arm, with the median and 5 / 10 mm marks."""
    arrays = {k: np.asarray(v, np.float64).reshape(-1) * 1000.0 for k, v in distances.items()}
    pooled = np.concatenate(list(arrays.values())) if arrays else np.empty(0)
    if pooled.size == 0:
        raise EvaluationError("no held-out distances to draw")
    top = max_mm if max_mm is not None else max(12.0, float(np.percentile(pooled, 99.5)))
    edges = np.linspace(0.0, top, bins + 1)
    fig = Figure(figsize=(8, 4.8))
    ax = fig.subplots()
    for k, (name, d) in enumerate(arrays.items()):
        if d.size:
            # matplotlib's stubs want bins as a Sequence; it takes numpy's array-like bin edges as well
            ax.hist(np.minimum(d, top), bins=edges, histtype="step", linewidth=1.4,  # type: ignore[arg-type]
                    color=arm_colour(name, k), label=f"{name}: {d.size:,} pts, median {np.median(d):.2f} mm")
    ax.hist(np.minimum(pooled, top), bins=edges, histtype="stepfilled",  # type: ignore[arg-type]  # (as above)
            color="0.6", alpha=0.35, label=f"all: {pooled.size:,} pts")
    median = float(np.median(pooled))
    ax.axvline(median, color="k", linewidth=1.2, label=f"median {median:.2f} mm")
    for mark, style in ((5.0, "--"), (10.0, ":")):
        if mark <= top:
            share = 100.0 * np.mean(pooled <= mark)
            ax.axvline(mark, color="0.3", linestyle=style, linewidth=1.0, label=f"{share:.1f}% within {mark:g} mm")
    ax.set_xlabel("held-out point-to-mesh distance [mm] (last bin: beyond)")
    ax.set_ylabel("points")
    ax.set_xlim(0.0, top)
    ax.legend(fontsize=8)
    ax.set_title(title or "Held-out RGB-D points against the measured-surface mesh")
    fig.tight_layout()
    return _save(fig, out)


__all__ = ["cross_arm_figure", "heldout_histogram", "partial_fused_figure"]
