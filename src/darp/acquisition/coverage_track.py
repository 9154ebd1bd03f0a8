"""Achieved coverage: what the recorded depth observed of the envelope's surface, per face, and the next
best views that look for what is still missing (the model is :mod:`darp.acquisition.coverage`).

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

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from darp.acquisition.coverage import (
    FACE_NAMES,
    FACES,
    Array,
    BoolArray,
    CoveragePrediction,
    CoverageSettings,
    SurfaceSamples,
    predict,
    visibility,
)
from darp.acquisition.coverage_plan import CoveragePlan
from darp.acquisition.estimate import fit_table_plane
from darp.acquisition.motion_check import ArmCollisionModel, MotionSettings, UnsafeMoveError, checked_move
from darp.acquisition.viewpoints import Candidate, ViewPlan
from darp.backend import RigBackend
from darp.formats.realsense.types import Intrinsics


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


def observe_live(backend: RigBackend, tracker: CoverageTracker, arm_id: str, model: ArmCollisionModel) -> None:
    """Add the arm's live depth at its present pose to the achieved coverage."""
    frames = backend.cameras[arm_id].latest_frameset()
    q = np.asarray(backend.arms[arm_id].read_state().q_rad, dtype=float)
    tracker.observe(arm_id, frames.depth_m, frames.depth_intrinsics, model.T_world_cam(q))


def visit_next_best_views(backend: RigBackend, tracker: CoverageTracker, arm_id: str, plan: ViewPlan,
                          model: ArmCollisionModel, later: list[str], tour_s: float, coverage: CoverageSettings,
                          motion: MotionSettings, events: Callable[..., None]) -> None:
    """Visit the next best views of ``arm_id`` (see :class:`CoverageTracker`), appending them to its plan,
    within ``coverage.nbv_time_fraction`` of ``tour_s`` (the time its planned views took)."""
    if arm_id not in tracker.plan.pools:
        return
    clock = backend.clock
    budget_s = coverage.nbv_time_fraction * tour_s
    per_view_s = tour_s / max(1, len(plan.views))  # a view's expected time: the planned views' mean
    tracker.budget_s[arm_id] = budget_s
    t0 = clock.now()
    for cand in tracker.next_views(arm_id, plan.views, later):
        spent = clock.now() - t0
        if spent + per_view_s > budget_s:
            events("next_best_view_budget", arm=arm_id, spent_s=round(spent, 3), budget_s=round(budget_s, 3),
                   per_view_s=round(per_view_s, 3))
            break
        q_now = np.asarray(backend.arms[arm_id].read_state().q_rad, dtype=float)
        if float(np.max(np.abs(cand.joints_rad - q_now))) > coverage.max_joint_step_rad:
            continue
        try:
            took = checked_move(backend, model, cand.joints_rad, motion)
        except UnsafeMoveError as err:
            events("next_best_view_refused", arm=arm_id, candidate=cand.index, reason=str(err))
            continue
        plan.views.append(cand)
        tracker.extra[arm_id].append(cand)
        observe_live(backend, tracker, arm_id, model)
        tracker.extra_s[arm_id] = clock.now() - t0
        events("next_best_view", arm=arm_id, candidate=cand.to_record(), move_s=round(took, 3),
               achieved=round(float(np.mean(tracker.union())), 4))


def coverage_record(strategy: str, plan: CoveragePlan | None, tracker: CoverageTracker | None
                    ) -> dict[str, Any] | None:
    """A survey's predicted and achieved coverage of the envelope's surface, for ``manip_envelope.json`` and
    ``verification.json`` (None without a coverage plan)."""
    if plan is None:
        return None
    record: dict[str, Any] = {"strategy": strategy, "samples": len(plan.samples),
                              "predicted": plan.prediction.to_record()}
    if tracker is not None and any(m.any() for m in tracker.observed.values()):
        record["achieved"] = tracker.achieved().to_record()
        record["next_best_views"] = {a: len(v) for a, v in tracker.extra.items()}
        record["next_best_views_s"] = {a: round(t, 3) for a, t in tracker.extra_s.items()}
        record["next_best_views_budget_s"] = {a: round(t, 3) for a, t in tracker.budget_s.items()}
        record["envelope_check"], record["envelope_warning"] = tracker.envelope_check()
    return record


__all__ = ["CoverageTracker", "coverage_record", "envelope_cut", "observe_live", "observed_samples", "ray_outcomes",
           "visit_next_best_views"]
