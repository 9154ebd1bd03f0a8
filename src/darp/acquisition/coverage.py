"""Coverage-driven viewpoints: plan both arms' views from the visibility of the envelope's surface,
with a co-observed band between the arms, and measure the coverage the recorded depth achieved.

**Surface.** The confirmed envelope (a vertical cylinder standing on the table) is sampled about every
``spacing_m`` on its side and its top (:func:`envelope_surface`); every sample has an outward normal
and a face label: ``+x``, ``-x`` (the sides facing arm111 and arm110 on the default rig), ``+y``, ``-y``
(the sides between the arms) and ``top``.

**Predicted visibility** (:func:`visibility`). A camera at ``c`` looking at the envelope's centre sees a
sample ``p`` when the sample faces it (incidence angle between the normal and ``c - p`` at most
``max_incidence_deg``), ``p`` lies inside the view cone (``half_fov_deg``) and its depth along the
optical axis is within ``[min_depth_m, max_depth_m]``. The envelope is convex, so facing is also
not self-occluded.

This module is the coverage model (settings, surface samples, visibility, predictions); planning with it is
:mod:`darp.acquisition.coverage_plan`, and measuring what a survey achieved, with the next best views,
:mod:`darp.acquisition.coverage_track`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

COVERAGE_ROLL_HINTS_DEG = (0.0, 90.0, -90.0, 180.0)  # fewer image rolls than the orbit's: many candidates
FACES = ("+x", "-x", "+y", "-y", "top")
FACE_NAMES = {"+x": "the +x side (towards arm111)", "-x": "the -x side (towards arm110)",
              "+y": "the +y side (between the arms, away from the operator)",
              "-y": "the -y side (between the arms, towards the operator)", "top": "the top"}


@dataclass(frozen=True)
class CoverageSettings:
    """Coverage planning: the candidate grid, the visibility model and the targets."""

    spacing_m: float = 0.01  # surface sample spacing on the envelope
    elevations_deg: tuple[float, ...] = (15.0, 40.0, 65.0, 88.0)
    azimuth_step_deg: float = 25.0
    azimuth_reach_deg: float = 100.0  # candidates within this of the arm's side (world azimuth)
    standoff_step_m: float = 0.06  # a candidate infeasible at the orbit's standoff is retried this much nearer/further
    max_incidence_deg: float = 60.0  # a sample counts as seen up to this incidence angle
    good_incidence_deg: float = 35.0  # and as well seen (low depth noise) up to this one
    half_fov_deg: float = 28.0  # the smaller half field of view of the D435 depth stream (58 deg / 2)
    max_depth_m: float = 1.2
    orbit_candidates: bool = True  # the paper orbit's feasible views are candidates too
    min_views: int = 8
    max_views: int = 12
    target_coverage: float = 0.98  # of what the feasible candidates can see
    target_co_observed: float = 0.25  # predicted share of covered samples that both arms see
    support_views: int = 3  # close sightings wanted per sample (fusion keeps voxels several frames and
    # direction bins saw; at high incidence the depth is noisy and the surface often lost)
    support_incidence_deg: float = 60.0  # a sighting supports a sample up to this incidence angle
    support_weight: float = 0.6  # gain of a further supporting sighting (up to support_views) against a first one
    target_support: float = 0.9  # of the samples support_views feasible candidates can support
    co_weight: float = 0.5
    # the co-observed band: side samples (the top of an open container is its opening: the arms see opposite
    # faces of its wall there) that each arm sees co_views times at most co_incidence_deg, so each arm's own
    # cloud can keep them (with fusion's arm_support_from_fused) and cross-arm consistency can compare them,
    # until target_co_sides of the covered side samples are in it (or 90 % of what the feasible views allow)
    co_views: int = 1
    co_incidence_deg: float = 60.0
    target_co_sides: float = 0.0  # off by default: on the twin it gained nothing (docs/acquisition.md); try 0.25
    co_band_weight: float = 1.0
    min_gain: float = 0.01  # a pick must add this share of the surface (after the co-observed target)
    warn_below: float = 0.8  # a face covered less than this (predicted or reachable) is warned about
    depth_tolerance_m: float = 0.015  # achieved coverage: depth within this of the envelope interval
    max_joint_step_rad: float = 2.6  # between consecutive views (every move is path-checked for clearance)
    nbv_max_views: int = 3  # extra views per arm from the next-best-view loop
    nbv_min_gain: float = 0.02  # an extra view must see this share of the surface still unobserved
    nbv_support_views: int = 2  # ... or observed by fewer than this many recorded views (1: unobserved only)
    # the loop's time budget: an arm's next best views may add at most this share of the time its planned views
    # took (a view is not started when the time spent plus one planned view's mean time would exceed it), so a
    # coverage survey stays within about 1.5x the orbit's time (its planned tour: 1.07-1.20x the orbit's)
    nbv_time_fraction: float = 0.25


@dataclass(frozen=True)
class SurfaceSamples:
    """Samples of the envelope's surface: points, outward normals and face labels (see :data:`FACES`)."""

    points: Array
    normals: Array
    faces: NDArray[np.str_]
    centre_m: Array
    radius_m: float
    height_m: float
    table_z_m: float

    def __len__(self) -> int:
        return len(self.points)

    def face_mask(self, face: str) -> BoolArray:
        return np.asarray(self.faces == face)


def envelope_surface(centre_m: Array, radius_m: float, height_m: float, table_z_m: float,
                     spacing_m: float = 0.01) -> SurfaceSamples:
    """Samples about ``spacing_m`` apart on the envelope cylinder's side and top (the bottom stands on
    the table and cannot be seen)."""
    c = np.asarray(centre_m, dtype=float)
    r, h = float(radius_m), float(height_m)
    n_az = 4 * max(6, math.ceil(2 * math.pi * r / spacing_m / 4))  # a multiple of 4: equal sides
    n_z = max(3, math.ceil(h / spacing_m))
    a = (np.arange(n_az) + 0.5) * 2 * math.pi / n_az
    z = table_z_m + (np.arange(n_z) + 0.5) * h / n_z
    A, Z = np.meshgrid(a, z, indexing="ij")
    side_n = np.stack([np.cos(A), np.sin(A), np.zeros_like(A)], axis=-1).reshape(-1, 3)
    side_p = np.column_stack([c[0] + r * side_n[:, 0], c[1] + r * side_n[:, 1], Z.reshape(-1)])
    side_az = np.degrees(A.reshape(-1))
    side_faces = np.where((side_az < 45) | (side_az >= 315), "+x",
                          np.where(side_az < 135, "+y", np.where(side_az < 225, "-x", "-y")))
    top = [np.array([c[0], c[1]])]
    for k in range(1, max(1, math.ceil(r / spacing_m)) + 1):
        rk = min(r, k * spacing_m) * 0.999
        m = max(6, math.ceil(2 * math.pi * rk / spacing_m))
        ak = (np.arange(m) + 0.5 * (k % 2)) * 2 * math.pi / m
        top.extend(np.column_stack([c[0] + rk * np.cos(ak), c[1] + rk * np.sin(ak)]))
    top_xy = np.array(top)
    top_p = np.column_stack([top_xy, np.full(len(top_xy), table_z_m + h)])
    points = np.vstack([side_p, top_p])
    normals = np.vstack([side_n, np.tile([0.0, 0.0, 1.0], (len(top_p), 1))])
    faces = np.concatenate([side_faces, np.full(len(top_p), "top")])
    return SurfaceSamples(points, normals, faces, c, r, h, float(table_z_m))


def visibility(samples: SurfaceSamples, cameras_m: Array, settings: CoverageSettings | None = None,
               min_depth_m: float = 0.17) -> BoolArray:
    """(V, N): which samples each camera (optical centres (V, 3), looking at the envelope's centre) sees."""
    s = settings if settings is not None else CoverageSettings()
    C = np.atleast_2d(np.asarray(cameras_m, dtype=float))
    centre = samples.centre_m.copy()
    centre[2] = samples.table_z_m + 0.5 * samples.height_m
    axis = centre[None] - C
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    d = samples.points[None] - C[:, None]  # (V, N, 3)
    dist = np.linalg.norm(d, axis=2)
    u = d / np.maximum(dist[..., None], 1e-12)
    facing = -np.einsum("vnk,nk->vn", u, samples.normals) >= math.cos(math.radians(s.max_incidence_deg))
    cos_axis = np.einsum("vnk,vk->vn", u, axis)
    depth = dist * cos_axis
    inside = cos_axis >= math.cos(math.radians(s.half_fov_deg))
    return np.asarray(facing & inside & (depth >= min_depth_m) & (depth <= s.max_depth_m))


@dataclass
class CoveragePrediction:
    """Predicted coverage of a plan: overall, per face, per arm, co-observed, and what no view reaches."""

    coverage: float  # share of all samples the planned views see
    reachable: float  # share any feasible candidate sees
    co_observed: float  # share of covered samples seen by both arms
    per_face: dict[str, float]
    reachable_per_face: dict[str, float]
    per_arm: dict[str, float]
    warnings: list[str] = field(default_factory=list)
    # share of covered samples that each arm sees at least twice (each arm's own cloud keeps such a surface:
    # what cross-arm consistency can measure), overall and on the sides only (an open container's top is
    # its opening: the arms see opposite faces of its wall there); None without sighting counts
    co_supported: float | None = None
    co_supported_sides: float | None = None
    # recorded depth only: share of samples whose rays met a surface inside the envelope or passed through it
    # to the far side (free space there: nothing to see); the per-face warnings count these, None for a plan
    resolved: float | None = None
    resolved_per_face: dict[str, float] | None = None

    def to_record(self) -> dict[str, Any]:
        def r(v: float | None) -> float | None:
            return None if v is None else round(v, 4)

        return {"coverage": round(self.coverage, 4), "reachable": round(self.reachable, 4),
                "co_observed": round(self.co_observed, 4), "co_supported": r(self.co_supported),
                "co_supported_sides": r(self.co_supported_sides),
                "per_face": {k: round(v, 4) for k, v in self.per_face.items()},
                "reachable_per_face": {k: round(v, 4) for k, v in self.reachable_per_face.items()},
                "per_arm": {k: round(v, 4) for k, v in self.per_arm.items()}, "warnings": list(self.warnings),
                **({} if self.resolved is None else {"resolved": round(self.resolved, 4)}),
                **({} if self.resolved_per_face is None
                   else {"resolved_per_face": {k: round(v, 4) for k, v in self.resolved_per_face.items()}})}


def _face_shares(samples: SurfaceSamples, seen: BoolArray) -> dict[str, float]:
    out = {}
    for face in FACES:
        mask = samples.face_mask(face)
        if mask.any():
            out[face] = float(np.mean(seen[mask]))
    return out


def predict(samples: SurfaceSamples, seen_by_arm: dict[str, BoolArray], reachable: BoolArray,
            warn_below: float = 0.8, by: str = "the planned views",
            counts_by_arm: dict[str, NDArray[np.int_]] | None = None,
            seen_through: BoolArray | None = None) -> CoveragePrediction:
    """Summarise per-arm visibility (each a (N,) mask) against the reachable mask; with per-arm sighting
    counts also the co-observed share supported in both arms (at least two sightings each). With
    ``seen_through`` (samples whose rays crossed the envelope without meeting a surface) a face counts as
    covered where its samples were seen or seen through: an object narrower than its envelope leaves free
    space there, not unseen surface."""
    arms = list(seen_by_arm)
    union = np.zeros(len(samples), dtype=bool)
    for m in seen_by_arm.values():
        union |= m
    both = np.ones(len(samples), dtype=bool)
    for m in seen_by_arm.values():
        both &= m
    per_face, reach_face = _face_shares(samples, union), _face_shares(samples, reachable)
    resolved = None if seen_through is None else union | seen_through
    covered_face = per_face if resolved is None else _face_shares(samples, resolved)
    warnings = []
    for face in FACES:
        if face in reach_face and reach_face[face] < warn_below:
            warnings.append(f"{FACE_NAMES[face]} cannot be reached: no feasible view sees "
                            f"{100 * (1 - reach_face[face]):.0f} % of it")
        elif face in covered_face and covered_face[face] < warn_below:
            warnings.append(f"{FACE_NAMES[face]} is only {100 * covered_face[face]:.0f} % covered by {by}")
    co_sup = co_sides = None
    if counts_by_arm is not None and len(arms) > 1:
        supported = np.logical_and.reduce([np.asarray(c) >= 2 for c in counts_by_arm.values()])
        sides = samples.faces != "top"
        co_sup = float(np.sum(supported) / max(1, np.sum(union)))
        co_sides = float(np.sum(supported & sides) / max(1, np.sum(union & sides)))
    return CoveragePrediction(
        coverage=float(np.mean(union)), reachable=float(np.mean(reachable)),
        co_observed=float(np.sum(both) / max(1, np.sum(union))) if len(arms) > 1 else 0.0,
        per_face=per_face, reachable_per_face=reach_face,
        per_arm={a: float(np.mean(m)) for a, m in seen_by_arm.items()}, warnings=warnings,
        co_supported=co_sup, co_supported_sides=co_sides,
        resolved=None if resolved is None else float(np.mean(resolved)),
        resolved_per_face=None if resolved is None else covered_face)


__all__ = ["FACES", "CoveragePrediction", "CoverageSettings", "SurfaceSamples", "envelope_surface", "predict",
           "visibility"]
