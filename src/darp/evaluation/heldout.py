"""Held-out evaluation: keyframes kept out of fusion, back-projected with their own poses, measured
against the measured-surface mesh (the paper's Table "Held-Out RGB-D Geometric Evaluation").

Each held-out frame goes through exactly the per-frame filters of fusion (depth range, discontinuity
rejection, incidence, the envelope crop) but not voxel support, which needs many frames. Every
surviving point's distance to the mesh is kept (float32), so statistics can be given per arm, per
object and pooled over objects (the paper pools 1,563,466 points of 224 keyframes).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from darp import paper
from darp.errors import EvaluationError
from darp.evaluation.point_to_mesh import DEFAULT_THRESHOLDS_M, DistanceStats, MeshDistance, distance_stats
from darp.reconstruction.backproject import PosedDepth, Region, backproject
from darp.reconstruction.fusion import FusionSettings


def heldout_mask(n_keyframes: int, every: int = 5, offset: int = 2) -> np.ndarray:
    """Deterministic split: keyframe i is held out when ``i % every == offset`` (True = held out).

    Spreading the held-out frames evenly along each arm's path makes them see the same surfaces as
    their fused neighbours from slightly different poses, which is what the evaluation measures.
    """
    if every < 2 or not 0 <= offset < every:
        raise EvaluationError(f"held-out split needs every >= 2 and 0 <= offset < every, got {every}, {offset}")
    heldout: np.ndarray = (np.arange(n_keyframes) % every) == offset
    return heldout


@dataclass(frozen=True, eq=False)
class HeldoutResult:
    """Distances of one object's held-out points to its mesh, per arm."""

    object_name: str
    distances: dict[str, np.ndarray]  # arm -> (N,) float32 metres
    frames: dict[str, int]  # arm -> held-out frames evaluated
    thresholds_m: tuple[float, ...] = DEFAULT_THRESHOLDS_M
    _stats: dict[str, DistanceStats] = field(default_factory=dict, repr=False)

    def stats(self, arm: str | None = None) -> DistanceStats:
        """Statistics of one arm's points, or of all arms together (``arm=None``)."""
        key = arm or "*"
        if key not in self._stats:
            if arm is None:
                parts = list(self.distances.values())
                d = np.concatenate(parts) if parts else np.empty(0, np.float32)
            else:
                d = self.distances.get(arm, np.empty(0, np.float32))
            self._stats[key] = distance_stats(d, self.thresholds_m)
        return self._stats[key]

    @property
    def n_frames(self) -> int:
        return int(sum(self.frames.values()))

    def to_dict(self) -> dict[str, Any]:
        return {
            "object": self.object_name,
            "keyframes": self.n_frames,
            "aggregate": self.stats().to_dict(),
            "arms": {arm: {"keyframes": self.frames.get(arm, 0), **self.stats(arm).to_dict()}
                     for arm in sorted(self.distances)},
        }


def heldout_points(frame: PosedDepth, settings: FusionSettings | None = None,
                   region: Region | None = None) -> np.ndarray:
    """World points (N, 3) float32 of one held-out frame after fusion's per-frame filters."""
    settings = settings or FusionSettings()
    return backproject(frame, settings.depth, region).points


def evaluate_heldout(frames: Iterable[PosedDepth], mesh: MeshDistance, *, object_name: str = "",
                     settings: FusionSettings | None = None, region: Region | None = None,
                     thresholds_m: Sequence[float] = DEFAULT_THRESHOLDS_M,
                     region_of: Callable[[PosedDepth], Region] | None = None) -> HeldoutResult:
    """Distances of every held-out frame's filtered points to ``mesh`` (streamed frame by frame).
    ``region_of(frame)``: a frame's own region (e.g. its fitted table crop) instead of ``region``."""
    settings = settings or FusionSettings()
    parts: dict[str, list[np.ndarray]] = {}
    counts: dict[str, int] = {}
    for frame in frames:
        points = heldout_points(frame, settings, region if region_of is None else region_of(frame))
        counts[frame.arm] = counts.get(frame.arm, 0) + 1
        parts.setdefault(frame.arm, []).append(mesh.distances(points) if len(points) else np.empty(0, np.float32))
    distances = {arm: np.concatenate(p).astype(np.float32) for arm, p in parts.items()}
    return HeldoutResult(object_name, distances, counts, tuple(float(t) for t in thresholds_m))


@dataclass(frozen=True, eq=False)
class HeldoutSummary:
    """Held-out results of several objects: one row each and the pooled aggregate."""

    results: tuple[HeldoutResult, ...]

    def aggregate(self, arm: str | None = None) -> DistanceStats:
        """Statistics pooled over every object's points (optionally of one arm)."""
        parts = [r.distances[a] for r in self.results for a in r.distances if arm is None or a == arm]
        thresholds = self.results[0].thresholds_m if self.results else DEFAULT_THRESHOLDS_M
        return distance_stats(np.concatenate(parts) if parts else np.empty(0, np.float32), thresholds)

    @property
    def n_frames(self) -> int:
        return sum(r.n_frames for r in self.results)

    def to_dict(self) -> dict[str, Any]:
        arms = sorted({a for r in self.results for a in r.distances})
        return {
            "objects": [r.to_dict() for r in self.results],
            "aggregate": {"keyframes": self.n_frames, **self.aggregate().to_dict()},
            "arms": {a: self.aggregate(a).to_dict() for a in arms},
            "paper": paper.HELDOUT,
        }

    def markdown(self) -> str:
        """The held-out table: one row per object, the aggregate, and the paper's numbers."""
        head = ("| object | keyframes | points | median [mm] | RMSE [mm] | p90 [mm] | within 5 mm [%] | "
                "within 10 mm [%] |\n|---|---:|---:|---:|---:|---:|---:|---:|")
        rows = [_row(r.object_name or "-", r.n_frames, r.stats()) for r in self.results]
        rows.append(_row("**all**", self.n_frames, self.aggregate()))
        p = paper.HELDOUT
        rows.append(f"| paper (DARP) | {p['keyframes']} | {p['points']:,} | {p['median_mm']:.2f} | "
                    f"{p['rmse_mm']:.2f} | {p['p90_mm']:.2f} | {p['within_5mm_pct']:.2f} | "
                    f"{p['within_10mm_pct']:.2f} |")
        return "\n".join([head, *rows]) + "\n"


def _row(name: str, frames: int, s: DistanceStats) -> str:
    def mm(v: float) -> str:
        return "-" if np.isnan(v) else f"{v * 1000.0:.2f}"

    def pct(t: float) -> str:
        v = s.within_pct.get(t, float("nan"))
        return "-" if np.isnan(v) else f"{v:.2f}"

    return (f"| {name} | {frames} | {s.count:,} | {mm(s.median_m)} | {mm(s.rmse_m)} | {mm(s.p90_m)} | "
            f"{pct(0.005)} | {pct(0.01)} |")


__all__ = ["HeldoutResult", "HeldoutSummary", "evaluate_heldout", "heldout_mask",
           "heldout_points"]
