"""Coverage planning: both arms' views chosen from the predicted visibility of the envelope's surface
(:mod:`darp.acquisition.coverage`), with a co-observed band between the arms.

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
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from darp.acquisition.coverage import (
    COVERAGE_ROLL_HINTS_DEG,
    Array,
    BoolArray,
    CoveragePrediction,
    CoverageSettings,
    SurfaceSamples,
    envelope_surface,
    predict,
    visibility,
)
from darp.acquisition.tour import tour_cost
from darp.acquisition.viewpoints import SHOULDER_BASE_M, Candidate, OrbitShape, ViewPlan, ViewpointPlanner


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


def survey_feasible_poses(planners: dict[str, ViewpointPlanner], plans: dict[str, ViewPlan], plan: CoveragePlan | None,
                          settings: CoverageSettings, coverage_strategy: bool) -> dict[str, list[list[float]]]:
    """A survey's feasible camera poses, the same whatever the strategy: the coverage grid's feasible candidates,
    the orbit's views and the views planned (checked after planning: no planner state the plans use moves)."""
    coverage = coverage_strategy and plan is not None
    grid = dict(plan.pools) if coverage and plan else feasible_pool(planners, settings)
    orbit = {a: p.plan().views for a, p in planners.items()} if coverage else {}
    pools: dict[str, list[Candidate]] = {}
    for a, arm_plan in plans.items():
        pool = list(grid.get(a, []))
        for v in [*orbit.get(a, []), *arm_plan.views]:
            if all(v is not c for c in pool):
                pool.append(v)
        pools[a] = pool
    return feasible_poses_record(planners, pools)


__all__ = ["CoveragePlan", "candidate_grid", "coverage_of_plans", "feasible_pool", "feasible_poses_record",
           "plan_coverage", "survey_feasible_poses"]
