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

**Planning** (:func:`plan_coverage`). Each arm's candidates are camera positions on a dense grid of
elevations and world azimuths within ``azimuth_reach_deg`` of the arm's side (so the +-y faces are
looked at square on) at the orbit's standoff and a larger one; every candidate goes through the
viewpoint planner's feasibility checks (IK, joint limits, workspace, minimum depth, table, self,
parked arm, envelope). A greedy set cover over both arms then picks the view with the largest gain,
where gain = newly covered samples + ``co_weight`` x samples the other arm already sees and this
arm does not (the co-observed band), until the union covers ``target_coverage`` of what the
feasible candidates can see and the co-observed share reaches ``target_co_observed``, with
``min_views`` .. ``max_views`` per arm. Each arm's picks are ordered and path-checked by
:meth:`~darp.acquisition.viewpoints.ViewpointPlanner._tour` (which may drop some), and the
prediction is recomputed on what is left.

**Achieved coverage** (:class:`CoverageTracker`). At every recorded view the live depth frame is
compared with the samples the view should see: a sample counts as observed when the depth at its pixel
lies between the sample's own depth (less a tolerance) and where the ray leaves the envelope (plus
the tolerance), i.e. the ray entered the envelope at the sample and met a surface inside it. A ray that
crossed the whole envelope and met something beyond it saw free space (an object narrower than its
envelope): its sample is "seen through", which the per-face warnings count as covered, while the next
best views still look for surface there. Samples no feasible candidate can see are reported per face as
unreachable (a warning naming the side).

**Next best view.** After an arm's planned views the survey asks :meth:`CoverageTracker.next_views`
for candidates of that arm that see the most still-unobserved samples (at least ``nbv_min_gain`` of
the surface each, at most ``nbv_max_views`` per arm) and visits them before parking, within a time budget
(``nbv_time_fraction`` of the time the arm's planned views took).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from darp.acquisition.estimate import fit_table_plane
from darp.acquisition.viewpoints import SHOULDER_BASE_M, Candidate, OrbitShape, ViewPlan, ViewpointPlanner, tour_cost
from darp.formats.realsense.types import Intrinsics

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


@dataclass
class CoveragePlan:
    """Both arms' plans, their candidate pools with visibility, and the prediction."""

    plans: dict[str, ViewPlan]
    samples: SurfaceSamples
    pools: dict[str, list[Candidate]]  # feasible candidates per arm
    pool_vis: dict[str, BoolArray]  # (len(pool), N) visibility per arm
    prediction: CoveragePrediction
    settings: CoverageSettings

    def view_visibility(self, arm_id: str, cand: Candidate) -> BoolArray:
        pool = self.pools[arm_id]
        row: BoolArray = self.pool_vis[arm_id][next(i for i, c in enumerate(pool) if c is cand)]
        return row


def candidate_grid(planner: ViewpointPlanner, shape: OrbitShape, settings: CoverageSettings,
                   standoff_m: float | None = None) -> list[Candidate]:
    """Camera positions on elevation rings and world azimuths within ``azimuth_reach_deg`` of the arm's
    side, at ``standoff_m`` (default: the orbit's)."""
    s = settings
    standoff = shape.standoff_m if standoff_m is None else standoff_m
    out: list[Candidate] = []
    n_half = int(s.azimuth_reach_deg // s.azimuth_step_deg)
    offsets = np.arange(-n_half, n_half + 1) * s.azimuth_step_deg
    for elev in s.elevations_deg:
        for off in offsets:
            az = planner.side_azimuth_deg + float(off)
            e, a = math.radians(elev), math.radians(az)
            direction = np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
            out.append(Candidate(len(out), float(elev), float(az), standoff, planner.centre + standoff * direction))
    return out


def _retry(planner: ViewpointPlanner, cand: Candidate, standoff_m: float, q_init: Array) -> bool:
    """Check ``cand`` moved to ``standoff_m`` along its direction; restores it and returns False on failure."""
    saved = (cand.standoff_m, cand.camera_m, cand.reason, cand.detail, cand.q_rad)
    direction = (cand.camera_m - planner.centre) / cand.standoff_m
    cand.standoff_m, cand.camera_m = standoff_m, planner.centre + standoff_m * direction
    planner.check_candidate(cand, q_init=q_init)
    if cand.ok:
        return True
    cand.standoff_m, cand.camera_m, cand.reason, cand.detail, cand.q_rad = saved
    return False


def _check_pool(planner: ViewpointPlanner, cands: list[Candidate], step_m: float) -> list[Candidate]:
    """Check every candidate (IK seeded from the previous feasible one, else from park). A camera
    position far beyond the arm's reach is rejected without IK (``workspace``); a candidate out of
    reach (``ik``, ``workspace``) is retried ``step_m`` nearer (not below the minimum depth plus the
    envelope's radius), one too near (``min_depth``, ``envelope``, ``table``, ``parked_arm``) further."""
    m = planner.model
    shoulder = (m.T_world_base @ np.r_[SHOULDER_BASE_M, 1.0])[:3]
    limit = planner.settings.reach_limit_m + 0.10  # flange reach plus the wrist-to-camera distance
    nearest = planner.settings.min_depth_m + planner.radius + 0.03
    q_prev = planner.q_park
    hints, planner.roll_hints_deg = planner.roll_hints_deg, COVERAGE_ROLL_HINTS_DEG
    for cand in cands:
        if float(np.linalg.norm(cand.camera_m - shoulder)) > limit + step_m:
            cand.ok, cand.reason, cand.detail = False, "workspace", "camera position beyond the arm's reach"
            continue
        planner.check_candidate(cand, q_init=q_prev)
        if not cand.ok and cand.reason == "ik" and q_prev is not planner.q_park:
            planner.check_candidate(cand, q_init=planner.q_park)
        if not cand.ok and step_m > 0:
            if cand.reason in ("ik", "workspace", "joint_limits") and cand.standoff_m - step_m >= nearest:
                _retry(planner, cand, cand.standoff_m - step_m, q_prev)
            elif cand.reason in ("min_depth", "envelope", "table", "parked_arm", "self"):
                _retry(planner, cand, cand.standoff_m + step_m, q_prev)
        if cand.ok:
            q_prev = cand.joints_rad
    planner.roll_hints_deg = hints
    return [c for c in cands if c.ok]


def _greedy(vis: dict[str, BoolArray], good: dict[str, BoolArray], sup: dict[str, BoolArray], reachable: BoolArray,
            s: CoverageSettings, banned: dict[str, set[int]], min_views: dict[str, int],
            co_vis: dict[str, BoolArray] | None = None, sides: BoolArray | None = None) -> dict[str, list[int]]:
    """Pick pool indices per arm (see the module docstring): first sightings (``vis``), then supporting
    sightings (``sup``: at most ``support_incidence_deg``) up to ``support_views`` per sample (fusion keeps a
    voxel only when several frames from distinct directions saw it), good-incidence sightings (``good``)
    and, until the co-observed target is met, the co-observed band (samples the other arm sees, up to
    ``support_views`` supporting sightings by this arm, so both arms' own clouds keep them). With ``co_vis`` (close
    sightings, at most ``co_incidence_deg``) and ``sides`` (the side samples), the **co-observed band**: side
    samples that another arm sees closely and this one has fewer than ``co_views`` close sightings of gain
    ``co_band_weight`` each, until ``target_co_sides`` of the covered side samples are seen ``co_views`` times
    closely by every arm (the band is left alone where the feasible views cannot reach that share)."""
    arms = list(vis)
    n = reachable.size
    band = co_vis is not None and sides is not None and len(arms) > 1
    co_count = {a: np.zeros(n, dtype=np.int32) for a in arms}
    co_f = {a: (co_vis[a] if co_vis is not None else vis[a]).astype(np.float64) for a in arms}
    side_mask = sides if sides is not None else np.zeros(n, dtype=bool)
    if band:  # the band the feasible views allow: side samples every arm's pool sees co_views times closely
        possible = np.logical_and.reduce([co_f[a].sum(axis=0) >= s.co_views for a in arms]) & side_mask
        reach_sides = max(1, int(np.sum(reachable & side_mask)))
        band_target = min(s.target_co_sides, 0.9 * float(np.sum(possible)) / reach_sides)
    k = max(1, s.support_views)
    picked: dict[str, list[int]] = {a: [] for a in arms}
    count = {a: np.zeros(n, dtype=np.int32) for a in arms}  # first sightings (any incidence)
    support = {a: np.zeros(n, dtype=np.int32) for a in arms}  # supporting sightings
    seen_good = np.zeros(n, dtype=bool)
    vis_f = {a: vis[a].astype(np.float64) for a in arms}
    sup_f = {a: sup[a].astype(np.float64) for a in arms}
    reach_k = np.sum([v.sum(axis=0) for v in sup_f.values()], axis=0) >= k
    target = s.target_coverage * max(1, int(np.sum(reachable)))
    target_k = s.target_support * max(1, int(np.sum(reach_k)))
    while True:
        union = np.logical_or.reduce([count[a] > 0 for a in arms])
        total_sup = np.sum([support[a] for a in arms], axis=0)
        both = np.logical_and.reduce([count[a] > 0 for a in arms]) if len(arms) > 1 else np.zeros(n, bool)
        co_share = float(np.sum(both) / max(1, np.sum(union))) if len(arms) > 1 else 1.0
        band_met = True
        if band:
            in_band = np.logical_and.reduce([co_count[a] >= s.co_views for a in arms]) & side_mask
            band_met = float(np.sum(in_band)) / max(1, int(np.sum(union & side_mask))) >= band_target
        done = (np.sum(union) >= target and np.sum(total_sup >= k) >= target_k and co_share >= s.target_co_observed
                and band_met)
        short = [a for a in arms if len(picked[a]) < min_views[a]]
        first = (~union).astype(np.float64)
        more = (total_sup < k).astype(np.float64) * s.support_weight
        new_good = (~seen_good).astype(np.float64) * 0.5
        best: tuple[float, str, int] | None = None
        for a in arms:
            if len(picked[a]) >= s.max_views or (done and a not in short):
                continue
            others = (np.logical_or.reduce([count[b] > 0 for b in arms if b != a]) if len(arms) > 1
                      else np.zeros(n, bool))
            co = (others & (support[a] < k)).astype(np.float64) * (0.0 if co_share >= s.target_co_observed
                                                                   else s.co_weight)
            own = (count[a] == 0).astype(np.float64) * 1e-3
            scores = vis_f[a] @ (first + own) + sup_f[a] @ (more + co) + good[a].astype(np.float64) @ new_good
            if band and not band_met:
                others_close = np.logical_or.reduce([co_count[b] > 0 for b in arms if b != a])
                want = side_mask & others_close & (co_count[a] < s.co_views)
                scores = scores + co_f[a] @ (want * s.co_band_weight)
            for i in np.argsort(-scores, kind="stable"):
                if int(i) in banned[a] or int(i) in picked[a]:
                    continue
                if best is None or scores[i] > best[0] + 1e-9:
                    best = (float(scores[i]), a, int(i))
                break
        if best is None:
            break
        score, a, i = best
        if not short and (done or score < s.min_gain * n):
            break
        picked[a].append(i)
        count[a] += vis[a][i]
        support[a] += sup[a][i]
        co_count[a] += co_vis[a][i] if co_vis is not None else vis[a][i]
        seen_good |= good[a][i]
    return picked


def plan_coverage(planners: dict[str, ViewpointPlanner], settings: CoverageSettings | None = None) -> CoveragePlan:
    """Plan every arm's views for coverage with a co-observed band (see the module docstring)."""
    from darp.acquisition.viewpoints import orbit_shape

    s = settings if settings is not None else CoverageSettings()
    arms = list(planners)
    first = planners[arms[0]]
    samples = envelope_surface(first.centre, first.radius, first.height, first.table.height_m, s.spacing_m)
    shape = orbit_shape(first.radius, first.height)
    good_s = CoverageSettings(max_incidence_deg=s.good_incidence_deg, half_fov_deg=s.half_fov_deg,
                              max_depth_m=s.max_depth_m)
    sup_s = replace(good_s, max_incidence_deg=s.support_incidence_deg)
    co_s = replace(good_s, max_incidence_deg=s.co_incidence_deg)
    co_vis: dict[str, BoolArray] = {}
    sup: dict[str, BoolArray] = {}
    vis: dict[str, BoolArray] = {}
    good: dict[str, BoolArray] = {}
    n = len(samples)
    all_cands = {arm_id: candidate_grid(planner, shape, s) for arm_id, planner in planners.items()}
    pools = {arm_id: _check_pool(planner, all_cands[arm_id], s.standoff_step_m) for arm_id, planner in planners.items()}
    if s.orbit_candidates:  # the orbit's views (with its relaxations) join the pool: coverage can pick them too
        for arm_id, planner in planners.items():
            pools[arm_id] = pools[arm_id] + list(planner.plan().views)
    for arm_id, planner in planners.items():
        cams = np.array([c.camera_m for c in pools[arm_id]]).reshape(-1, 3)
        md = planner.settings.min_depth_m
        vis[arm_id] = visibility(samples, cams, s, md) if len(cams) else np.zeros((0, n), dtype=bool)
        good[arm_id] = visibility(samples, cams, good_s, md) if len(cams) else np.zeros((0, n), dtype=bool)
        sup[arm_id] = visibility(samples, cams, sup_s, md) if len(cams) else np.zeros((0, n), dtype=bool)
        co_vis[arm_id] = visibility(samples, cams, co_s, md) if len(cams) else np.zeros((0, n), dtype=bool)
    reachable = np.logical_or.reduce([v.any(axis=0) for v in vis.values()])
    banned: dict[str, set[int]] = {a: set() for a in arms}
    min_views = {a: min(s.min_views, len(pools[a])) for a in arms}
    tours: dict[str, list[Candidate]] = {}
    for _ in range(10):  # views the tour drops (joint motion, paths) are banned and the cover redone
        picked = _greedy(vis, good, sup, reachable, s, banned, min_views, co_vis, samples.faces != "top")
        dropped = False
        for a, planner in planners.items():
            chosen = [pools[a][i] for i in picked[a]]
            saved = planner.settings
            planner.settings = replace(saved, max_joint_step_rad=s.max_joint_step_rad)
            try:
                tours[a] = planner._tour(chosen)
            finally:
                planner.settings = saved
            kept = {id(c) for c in tours[a]}
            for i in picked[a]:
                if id(pools[a][i]) not in kept:
                    banned[a].add(i)
                    dropped = True
            min_views[a] = min(min_views[a], len(pools[a]) - len(banned[a]))
        if not dropped:
            break
    plans: dict[str, ViewPlan] = {}
    final_seen: dict[str, BoolArray] = {}
    final_count: dict[str, NDArray[np.int_]] = {}
    for a, planner in planners.items():
        views = tours[a]
        rec = {"strategy": "coverage", "candidates": len(all_cands[a]), "feasible": len(pools[a]),
               "dropped_by_tour": len(banned[a]), "views": len(views),
               "rejected": _counts([c for c in all_cands[a] if not c.ok])}
        plan = ViewPlan(a, shape, views, all_cands[a], [rec])
        plan.travel_rad = tour_cost(planner.q_park, plan.q_views, planner.q_park)
        plans[a] = plan
        k = np.zeros(n, dtype=np.int_)
        for c in views:
            k += vis[a][pools[a].index(c)]
        final_seen[a], final_count[a] = k > 0, k
    prediction = predict(samples, final_seen, reachable, s.warn_below, counts_by_arm=final_count)
    return CoveragePlan(plans, samples, pools, vis, prediction, s)


def feasible_pool(planners: dict[str, ViewpointPlanner], settings: CoverageSettings | None = None
                  ) -> dict[str, list[Candidate]]:
    """Every arm's feasible candidates of the coverage grid (the pool :func:`plan_coverage` picks from)."""
    from darp.acquisition.viewpoints import orbit_shape

    s = settings if settings is not None else CoverageSettings()
    first = next(iter(planners.values()))
    shape = orbit_shape(first.radius, first.height)
    return {a: _check_pool(p, candidate_grid(p, shape, s), s.standoff_step_m) for a, p in planners.items()}


def feasible_poses_record(planners: dict[str, ViewpointPlanner], pools: dict[str, list[Candidate]]
                          ) -> dict[str, list[list[float]]]:
    """Per arm, the camera poses (``T_world_cam``'s top three rows, row-major, 12 numbers) of the feasible
    candidates: with the true mesh, evaluation computes the surface any feasible camera pose can see."""
    out: dict[str, list[list[float]]] = {}
    for a, pool in pools.items():
        model = planners[a].model
        out[a] = [[round(float(v), 6) for v in np.asarray(model.T_world_cam(c.joints_rad))[:3].reshape(-1)]
                  for c in pool]
    return out


def coverage_of_plans(planners: dict[str, ViewpointPlanner], plans: dict[str, ViewPlan],
                      settings: CoverageSettings | None = None) -> CoveragePlan:
    """The coverage bookkeeping of plans made otherwise (the paper's orbit): each arm's pool is its own
    views, so "reachable" means what those views can see and no next best view is ever proposed."""
    s = replace(settings if settings is not None else CoverageSettings(), nbv_max_views=0)
    first = next(iter(planners.values()))
    samples = envelope_surface(first.centre, first.radius, first.height, first.table.height_m, s.spacing_m)
    n = len(samples)
    pools = {a: list(p.views) for a, p in plans.items()}
    vis = {a: (visibility(samples, np.array([c.camera_m for c in pools[a]]), s, planners[a].settings.min_depth_m)
               if pools[a] else np.zeros((0, n), dtype=bool)) for a in plans}
    seen: dict[str, BoolArray] = {a: np.asarray(v.any(axis=0), dtype=bool) for a, v in vis.items()}
    reachable = np.logical_or.reduce(list(seen.values()))
    counts = {a: np.asarray(v.sum(axis=0), dtype=np.int_) for a, v in vis.items()}
    return CoveragePlan(dict(plans), samples, pools, vis,
                        predict(samples, seen, reachable, s.warn_below, counts_by_arm=counts), s)


def _counts(cands: list[Candidate]) -> dict[str, int]:
    out: dict[str, int] = {}
    for c in cands:
        out[c.reason] = out.get(c.reason, 0) + 1
    return out


# -- achieved coverage ---------------------------------------------------------------------------------
def observed_samples(samples: SurfaceSamples, depth_m: NDArray[np.floating[Any]], intrinsics: Intrinsics,
                     T_world_cam: Array, candidates: BoolArray | None = None,
                     tolerance_m: float = 0.015) -> BoolArray:
    """(N,): samples whose pixel in ``depth_m`` (metres, 0 invalid) shows a surface between the sample and
    where the ray leaves the envelope (see the module docstring); ``candidates`` restricts the test."""
    return ray_outcomes(samples, depth_m, intrinsics, T_world_cam, candidates, tolerance_m)[0]


def ray_outcomes(samples: SurfaceSamples, depth_m: NDArray[np.floating[Any]], intrinsics: Intrinsics,
                 T_world_cam: Array, candidates: BoolArray | None = None,
                 tolerance_m: float = 0.015) -> tuple[BoolArray, BoolArray]:
    """Per sample (N,) each: the ray through it met a surface inside the envelope (observed), or crossed the
    whole envelope and met something beyond it (seen through: free space, nothing there to see). Samples
    with no valid depth, or hidden by something in front of them, are neither."""
    n = len(samples)
    out, through = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
    idx = np.flatnonzero(candidates) if candidates is not None else np.arange(n)
    if idx.size == 0:
        return out, through
    T_cam_world = np.linalg.inv(np.asarray(T_world_cam, dtype=float))
    p = samples.points[idx]
    pc = p @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    z = pc[:, 2]
    front = z > 1e-3
    u = intrinsics.fx * pc[:, 0] / np.where(front, z, 1.0) + intrinsics.ppx
    v = intrinsics.fy * pc[:, 1] / np.where(front, z, 1.0) + intrinsics.ppy
    h, w = depth_m.shape
    ui, vi = np.round(u).astype(int), np.round(v).astype(int)
    inside = front & (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    d = np.zeros(len(idx))
    d[inside] = depth_m[vi[inside], ui[inside]]
    # where the ray from the camera through the sample leaves the envelope (its depth along the axis)
    cam = np.asarray(T_world_cam, dtype=float)[:3, 3]
    ray = p - cam
    length = np.linalg.norm(ray, axis=1)
    unit = ray / length[:, None]
    t_exit = _ray_exit(cam, unit, samples)
    z_exit = z * t_exit / length
    reached = inside & (d > 0) & (d >= z - tolerance_m)
    ok = reached & (d <= z_exit + tolerance_m)
    out[idx[ok]] = True
    through[idx[reached & ~ok]] = True
    return out, through


def _ray_exit(origin: Array, unit: Array, s: SurfaceSamples) -> Array:
    """Distance along each ray (from ``origin``) at which it leaves the envelope cylinder."""
    o = origin[:2] - s.centre_m[:2]
    dx, dy = unit[:, 0], unit[:, 1]
    a = dx * dx + dy * dy
    b = 2 * (o[0] * dx + o[1] * dy)
    c = o @ o - s.radius_m ** 2
    disc = np.maximum(b * b - 4 * a * c, 0.0)
    t_side = np.where(a > 1e-12, (-b + np.sqrt(disc)) / np.maximum(2 * a, 1e-12), np.inf)
    dz = unit[:, 2]
    with np.errstate(divide="ignore"):
        t_bottom = np.where(dz < -1e-9, (s.table_z_m - origin[2]) / dz, np.inf)
    return np.asarray(np.minimum(t_side, t_bottom))


def envelope_cut(samples: SurfaceSamples, depth_m: NDArray[np.floating[Any]], intrinsics: Intrinsics,
                 T_world_cam: Array, band_m: float = 0.05, table_gap_m: float = 0.008,
                 tolerance_m: float = 0.01, stride: int = 2, table_search_m: float = 0.03) -> dict[str, Any]:
    """Depth points of one frame inside the envelope and in a band ``band_m`` wide just outside it
    (beside or above; points within ``table_gap_m`` of the table are the table). Surface in that band
    is what the crop to the envelope would cut; counted per face by the direction it lies in.

    The table is the plane fitted to this frame's points within ``table_search_m`` of the nominal table
    height (the nominal height when too few are there): with a rig's real errors the table the calibrated
    kinematics place can sit 1-2 cm off the nominal one, and its points then counted as cut surface."""
    d = np.asarray(depth_m, dtype=float)[::stride, ::stride]
    v, u = np.nonzero(d > 0)
    z = d[v, u]
    x = (u * stride - intrinsics.ppx) / intrinsics.fx * z
    y = (v * stride - intrinsics.ppy) / intrinsics.fy * z
    T = np.asarray(T_world_cam, dtype=float)
    p = np.column_stack([x, y, z]) @ T[:3, :3].T + T[:3, 3]
    rel = p[:, :2] - samples.centre_m[:2]
    radial = np.hypot(rel[:, 0], rel[:, 1])
    plane = fit_table_plane(p, samples.table_z_m, table_search_m)
    table_z = samples.table_z_m if plane is None else p[:, 0] * plane[0][0] + p[:, 1] * plane[0][1] + plane[0][2]
    h = p[:, 2] - table_z
    above_table = h > table_gap_m
    r, top = samples.radius_m, samples.height_m
    inside = above_table & (radial <= r + tolerance_m) & (h <= top + tolerance_m)
    near = above_table & (radial <= r + band_m) & (h <= top + band_m)
    outside = near & ~inside
    az = np.degrees(np.arctan2(rel[outside, 1], rel[outside, 0])) % 360.0
    beside = radial[outside] > r + tolerance_m
    faces = np.where(~beside, "top", np.where((az < 45) | (az >= 315), "+x",
                                              np.where(az < 135, "+y", np.where(az < 225, "-x", "-y"))))
    return {"inside": int(np.sum(inside)), "outside": int(np.sum(outside)),
            "by_face": {f: int(np.sum(faces == f)) for f in FACES}}


class CoverageTracker:
    """Achieved coverage during a survey: observations per arm from live depth, and next best views."""

    def __init__(self, plan: CoveragePlan) -> None:
        self.plan = plan
        n = len(plan.samples)
        self.observed = {a: np.zeros(n, dtype=bool) for a in plan.plans}
        self.observed_count = {a: np.zeros(n, dtype=np.int_) for a in plan.plans}
        self.seen_through = np.zeros(n, dtype=bool)  # by any arm: rays that crossed the envelope (free space)
        self.extra: dict[str, list[Candidate]] = {a: [] for a in plan.plans}
        self.extra_s: dict[str, float] = dict.fromkeys(plan.plans, 0.0)  # rig time the next best views took
        self.budget_s: dict[str, float] = dict.fromkeys(plan.plans, 0.0)  # ... and the time they were allowed
        self.cut: dict[str, Any] = {"inside": 0, "outside": 0, "by_face": dict.fromkeys(FACES, 0)}

    def observe(self, arm_id: str, depth_m: NDArray[np.floating[Any]], intrinsics: Intrinsics,
                T_world_cam: Array) -> int:
        """Add one view's live depth; returns how many samples it observed."""
        cam = np.asarray(T_world_cam, dtype=float)[:3, 3]
        expect = visibility(self.plan.samples, cam[None], self.plan.settings, min_depth_m=0.0)[0]
        seen, through = ray_outcomes(self.plan.samples, depth_m, intrinsics, T_world_cam, expect,
                                     self.plan.settings.depth_tolerance_m)
        self.observed[arm_id] |= seen
        self.seen_through |= through
        self.observed_count[arm_id] += seen
        cut = envelope_cut(self.plan.samples, depth_m, intrinsics, T_world_cam)
        self.cut["inside"] += cut["inside"]
        self.cut["outside"] += cut["outside"]
        for face, k in cut["by_face"].items():
            self.cut["by_face"][face] += k
        return int(np.sum(seen))

    def envelope_check(self, warn_share: float = 0.05) -> tuple[dict[str, Any], str | None]:
        """The envelope against the recorded depth: the share of depth points near the object that lie just
        outside the envelope (what the crop would cut), and a warning naming the side when above ``warn_share``."""
        total = self.cut["inside"] + self.cut["outside"]
        share = self.cut["outside"] / total if total else 0.0
        record = {**self.cut, "outside_share": round(share, 4)}
        if share <= warn_share:
            return record, None
        worst = max(FACES, key=lambda f: self.cut["by_face"][f])
        return record, (f"the envelope may cut observed surface: {100 * share:.0f} % of the depth points near the "
                        f"object lie just outside it, most beyond {FACE_NAMES[worst]}; the crop would remove them "
                        "(check the calibration, or re-run the survey)")

    def union(self) -> BoolArray:
        u = np.zeros(len(self.plan.samples), dtype=bool)
        for m in self.observed.values():
            u |= m
        return u

    def next_views(self, arm_id: str, used: list[Candidate], remaining_arms: list[str]) -> list[Candidate]:
        """Candidates of ``arm_id`` (not yet used) that see the most samples the recorded depth showed in fewer
        than ``nbv_support_views`` views, best first. Fusion keeps surface that several frames from two
        viewing directions measured, so a sample one view glimpsed (the face of a thin plate between the arms,
        seen edge-on) is still a target, not only one no view saw.

        Samples the arms still to record (``remaining_arms``) are planned to see are not targets."""
        s, p = self.plan.settings, self.plan
        n = len(p.samples)
        seen_by = np.zeros(n, dtype=np.int_)
        for count in self.observed_count.values():
            seen_by += count
        target = seen_by < max(s.nbv_support_views, 1)
        for b in remaining_arms:
            for c in p.plans[b].views:
                target &= ~p.view_visibility(b, c)
        out: list[Candidate] = []
        pool = p.pools[arm_id]
        taken = {id(c) for c in used}
        for _ in range(s.nbv_max_views - len(self.extra[arm_id])):
            gains = [(float(np.sum(p.pool_vis[arm_id][i] & target)), i) for i, c in enumerate(pool)
                     if id(c) not in taken]
            if not gains:
                break
            gain, i = max(gains, key=lambda g: (g[0], -g[1]))
            if gain < s.nbv_min_gain * n:
                break
            out.append(pool[i])
            taken.add(id(pool[i]))
            target &= ~p.pool_vis[arm_id][i]
        return out

    def achieved(self) -> CoveragePrediction:
        """Achieved coverage (observed samples) in the prediction's terms."""
        reachable = np.zeros(len(self.plan.samples), dtype=bool)
        for v in self.plan.pool_vis.values():
            reachable |= v.any(axis=0)
        return predict(self.plan.samples, self.observed, reachable, self.plan.settings.warn_below,
                       by="the recorded depth", counts_by_arm=self.observed_count, seen_through=self.seen_through)


__all__ = ["FACES", "CoveragePlan", "CoveragePrediction", "CoverageSettings", "CoverageTracker", "SurfaceSamples",
           "coverage_of_plans", "envelope_cut", "feasible_pool", "feasible_poses_record",
           "candidate_grid", "envelope_surface", "observed_samples", "plan_coverage", "predict", "ray_outcomes",
           "visibility"]
