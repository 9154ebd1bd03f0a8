"""The representative multimodal observations figure (the paper's RGB / depth / IR left / IR right panel).

One row per (object, arm): the colour image, the metric depth colour-mapped (no depth: black), and
the left and right infrared images, all from one frame set of that arm's camera. The frame sets are
the ``keyframes/observations/<arm>.npz`` files the keyframe export writes (raw, unaligned colour);
a survey without them falls back to its first keyframe (colour aligned to depth).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from darp.errors import EvaluationError
from darp.formats.atomic import atomic_path
from darp.reconstruction.keyframe_io import OBSERVATIONS_DIR, iter_keyframes, read_observation

COLUMNS = (("rgb", "RGB"), ("depth", "depth"), ("ir_left", "IR left"), ("ir_right", "IR right"))
Observation = Mapping[str, np.ndarray]


def colour_mapped_depth(depth: np.ndarray, depth_scale: float, *, cmap: str = "turbo",
                        range_m: tuple[float, float] | None = None) -> np.ndarray:
    """(H, W, 3) uint8: metric depth through a colour map (2nd-98th percentile range), black without depth."""
    depth_m = np.asarray(depth, np.float64) * depth_scale
    valid = depth_m > 0
    out = np.zeros((*depth_m.shape, 3), np.uint8)
    if not valid.any():
        return out
    lo, hi = range_m if range_m is not None else tuple(np.percentile(depth_m[valid], [2.0, 98.0]))
    scaled = np.clip((depth_m - lo) / max(hi - lo, 1e-6), 0.0, 1.0)
    rgb = (colormaps[cmap](scaled)[..., :3] * 255.0).astype(np.uint8)
    out[valid] = rgb[valid]
    return out


def survey_observations(survey_out: str | Path) -> dict[str, dict[str, np.ndarray]]:
    """Frame sets by arm of a processed survey: ``observations/`` first, else its first keyframe per arm."""
    keyframes = Path(survey_out) / "keyframes"
    found: dict[str, dict[str, np.ndarray]] = {}
    folder = keyframes / OBSERVATIONS_DIR
    if folder.is_dir():
        for path in sorted(folder.glob("*.npz")):
            found[path.stem] = read_observation(path)
    if not found and (keyframes / "keyframes.json").is_file():
        for kf in iter_keyframes(keyframes):
            if kf.arm not in found:
                found[kf.arm] = {"rgb": kf.rgb, "depth": kf.depth, "ir_left": kf.ir_left, "ir_right": kf.ir_right,
                                 "depth_scale": np.array(kf.depth_scale, np.float64)}  # 0-d, as read from .npz
    return found


def observations_figure(rows: Sequence[tuple[str, Mapping[str, Observation]]], out: str | Path, *,
                        title: str = "", panel_width_in: float = 2.6) -> Path:
    """Draw ``rows`` = [(object name, {arm: frame set arrays}), ...] as one figure; written atomically."""
    lines = [(name, arm, obs) for name, arms in rows for arm, obs in sorted(arms.items())]
    if not lines:
        raise EvaluationError("no observations to draw (no processed survey has keyframes)")
    first = next(iter(lines))[2]
    h, w = np.asarray(first.get("depth", first.get("rgb"))).shape[:2]
    fig = Figure(figsize=(panel_width_in * len(COLUMNS), panel_width_in * h / w * len(lines) + 0.8))
    axes = np.atleast_2d(fig.subplots(len(lines), len(COLUMNS), squeeze=False))
    for r, (name, arm, obs) in enumerate(lines):
        for c, (key, label) in enumerate(COLUMNS):
            ax = axes[r, c]
            ax.set_xticks([])
            ax.set_yticks([])
            image = obs.get(key)
            if image is None:
                ax.text(0.5, 0.5, "missing", ha="center", va="center", transform=ax.transAxes)
            elif key == "depth":
                ax.imshow(colour_mapped_depth(image, float(obs.get("depth_scale", 0.001))))
            elif np.asarray(image).ndim == 2:
                ax.imshow(image, cmap="gray", vmin=0, vmax=255)
            else:
                ax.imshow(image)
            if r == 0:
                ax.set_title(label, fontsize=10)
            if c == 0:
                ax.set_ylabel(f"{name}\n{arm}", fontsize=9)
    fig.suptitle(title or "Representative multimodal observations (RGB, metric depth, IR left, IR right)")
    fig.tight_layout(rect=(0.0, 0.0, 1.0, 0.97))
    out = Path(out)
    FigureCanvasAgg(fig)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, format=out.suffix.lstrip(".") or "png", dpi=110)
    return out


__all__ = ["COLUMNS", "colour_mapped_depth", "observations_figure", "survey_observations"]
