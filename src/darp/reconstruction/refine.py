"""Survey-level pose refinement: small corrections to the keyframes' camera poses from the consistency of
overlapping depth (issue 16, item 4; ``corrections.refine``; docs/accuracy.md "Survey-level refinement").

The paper takes every camera pose from the calibration and the kinematics (eq. 1). Where two depth
views of the same surface disagree, at least one of those poses is wrong; this module finds world-frame
corrections ``C`` (``T_world_cam' = C @ T_world_cam``) that make the views agree, in two levels:

1. **Per arm** (arm-to-arm): the two arms' ``fuse`` keyframes, merged per arm, are aligned to each other;
   the rigid transform is split in half between the arms (its geometric mean), so the world frame does
   not move with it.
2. **Per view** (multi-view): each ``fuse`` keyframe is aligned to all the other ``fuse`` keyframes
   together, for ``rounds`` rounds (all views updated from the previous round's corrections); after each
   round the gauge is fixed: the corrections' mean (rotation mean and mean displacement of the envelope
   centre) is removed, so the world frame stays that of the calibration. Each arm's mean of its views'
   corrections is added to the arm's correction; the rest is the view's own.

Every alignment is a **regularised point-to-plane ICP** (a maximum a posteriori estimate,
:mod:`darp.reconstruction.registration`): Gauss-Newton on
the point-to-plane residuals (Tukey weights, nearest neighbours from a k-d tree, coarse to fine) plus a
Gaussian prior that holds the correction near identity with the calibration's stated uncertainty. Where
the overlap does not constrain a direction (a rotationally symmetric object turning about its axis, a
view sliding along the table plane, two arms that see opposite sides of the object), the prior keeps
the correction at zero instead of letting it drift; plain ICP (Open3D's, tried first) drifted by several
degrees there on the twin's mug survey. Open3D prepares the clouds (voxel downsampling).

**Bounds.** A correction is measured by the displacement it gives the envelope centre (mm) and its
rotation angle (deg). It is accepted only within ``max_sigma`` x the calibration's stated uncertainty
(the held-out p90 corner error, :func:`darp.reconstruction.fusion.calibration_uncertainty_m`; a default
when the calibration states none) and that length over ``lever_m`` as an angle; a larger one is refused:
an arm refused keeps its calibrated poses, a view refused keeps its arm's correction.

**The gate.** Every ``validate_every``-th fuse keyframe of each arm is left out of the fit (a validation
view; never one of the held-out split). After the fit, three levels are scored by how well the validation
views (at their arm's correction) lie on the fit views' surface (mean truncated point-to-plane distance):
no correction, the arms' corrections, and the arms' plus the views' own. The lowest is applied if it beats
no correction by ``gate_min_gain``; else nothing is. The costs and the decision go to the record (``gate``).
An arm with fewer than ``gate_min_views`` fuse keyframes: no gate (the record says so).

**Held-out keyframes** are never used to compute a correction. They receive their arm's correction (a
property of the arm's calibration, estimated from the ``fuse`` keyframes only) and no per-view correction,
so the held-out evaluation measures the refinement on views it did not see.

**What it can and cannot correct.** It removes view-to-view and arm-to-arm inconsistency (hand-eye,
joint-offset and base errors that move views differently). It cannot see an error shared by all views:
a common depth scale error, a rigid offset of the whole world frame (the gauge), or a bias that moves
every view the same way; and it needs overlapping surfaces (directions the overlap leaves unconstrained
stay uncorrected, held by the prior).
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from darp.errors import ReconstructionError
from darp.reconstruction.backproject import DepthFilterSettings, PosedDepth, backproject
from darp.reconstruction.crop import EnvelopeCrop
from darp.reconstruction.registration import (
    displacement_m,
    information_ratios,
    mean_transform,
    regularised_icp,
    rigid_power,
    rotation_angle_deg,
    transform_twist,
)

DEFAULT_UNCERTAINTY_M = 0.003  # used when the calibration states no held-out error


@dataclass(frozen=True)
class RefineSettings:
    """Parameters of the survey-level refinement (group ``refinement`` of the processing settings)."""

    per_arm: bool = True  # arm-to-arm rigid correction
    per_view: bool = True  # per-keyframe corrections (multi-view)
    rounds: int = 2  # per-view rounds (each view against all others, then the gauge fixed)
    voxel_size_m: float = 0.0025  # registration clouds are voxel-downsampled to this
    region_margin_m: float = 0.015  # the registration region: envelope crop grown radially by this ...
    table_depth_m: float = 0.015  # ... and reaching this far below the table plane (the table constrains z, tilt;
    # negative: starting this far above it, i.e. without the table)
    max_correspondence_m: tuple[float, ...] = (0.008, 0.004)  # ICP scales, coarse to fine
    iterations: int = 8  # Gauss-Newton iterations per scale
    tukey_k_m: float = 0.003  # robust kernel width at the finest scale (scaled with the correspondence distance)
    point_sigma_m: float = 0.002  # a point-to-plane residual's standard deviation (depth noise, surface fit)
    prior_sigma: float = 0.4  # prior per axis: this times the calibration's stated p90 error (3-D p90 ~ 2.5 sigma)
    min_overlap: float = 0.2  # an alignment whose inlier fraction is below this is not used
    max_sigma: float = 2.0  # bound: this times the calibration's stated uncertainty ...
    lever_m: float = 0.35  # ... as a length at the envelope centre, and as an angle over this lever
    min_points: int = 300  # a keyframe with fewer registration points takes no part
    max_source_points: int = 1500  # a view's points in its own alignment: an even subsample of this many (speed)
    min_normal_cos: float = 0.5  # a correspondence's normals (oriented toward their cameras) must agree this well
    heldout: str = "arm"  # held-out keyframes: "arm" (their arm's correction only) or "register" (also aligned,
    # alone, to the refined fuse keyframes, same prior and bounds: optimistic, see docs/accuracy.md)
    validate_every: int = 4  # the gate: every this-many-th fuse keyframe of an arm is left out of the fit and
    # checks it (0: no gate; never the held-out split)
    gate_min_views: int = 6  # ... only when every arm has at least this many fuse keyframes
    gate_min_gain: float = 0.02  # a level (arm, arm + view) is applied only if it lowers the validation cost
    # (mean truncated point-to-plane distance of the validation views to the fit views) by this fraction
    gate_truncate_m: float = 0.005  # the validation cost's truncation (an unmatched point costs this)
    gate_match_m: float = 0.01  # ... and its nearest-neighbour search radius

    def __post_init__(self) -> None:
        if not (1e-4 <= self.voxel_size_m <= 0.02 and self.region_margin_m >= 0 and self.table_depth_m >= -0.05):
            raise ReconstructionError("refinement: voxel_size_m must be within 0.1 mm .. 2 cm and margins >= 0")
        if not self.max_correspondence_m or any(not d > 0 for d in self.max_correspondence_m):
            raise ReconstructionError("refinement: max_correspondence_m must be a non-empty list of lengths > 0")
        if not (self.max_sigma > 0 and self.lever_m > 0 and self.tukey_k_m > 0 and self.point_sigma_m > 0
                and self.prior_sigma > 0 and 0 <= self.min_overlap <= 1):
            raise ReconstructionError("refinement: max_sigma, lever_m, tukey_k_m, point_sigma_m and prior_sigma must "
                                      "be > 0, min_overlap in [0, 1]")
        if self.heldout not in ("arm", "register"):
            raise ReconstructionError(f"refinement: heldout must be 'arm' or 'register', got {self.heldout!r}")
        if self.rounds < 1 or self.iterations < 1 or self.min_points < 10 or self.max_source_points < 10:
            raise ReconstructionError("refinement: rounds and iterations >= 1, min_points >= 10")
        if not (self.validate_every >= 0 and self.validate_every != 1 and self.gate_min_views >= 3
                and 0 <= self.gate_min_gain < 1 and self.gate_truncate_m > 0 and self.gate_match_m > 0):
            raise ReconstructionError("refinement: validate_every 0 or >= 2, gate_min_views >= 3, gate_min_gain in "
                                      "[0, 1), gate_truncate_m and gate_match_m > 0")


@dataclass(frozen=True)
class RefineView:
    """One keyframe as the refinement sees it: identity, split and pose (metres, world frame)."""

    key: str  # unique (e.g. the keyframe file)
    arm: str
    frame_number: int
    split: str  # "fuse" or "heldout"
    T_world_cam: np.ndarray


@dataclass
class RefineResult:
    """The corrected poses by view key and the record of what was done (for results.json)."""

    poses: dict[str, np.ndarray]
    record: dict[str, Any]


# -- registration clouds ---------------------------------------------------------------------------------
def registration_region(crop: EnvelopeCrop, settings: RefineSettings) -> EnvelopeCrop:
    """The envelope crop grown by ``region_margin_m`` and reaching ``table_depth_m`` below the table."""
    return EnvelopeCrop(center_m=crop.center_m, radius_m=crop.radius_m, height_m=crop.height_m,
                        table_z_m=crop.table_z_m, margin_m=crop.margin_m + settings.region_margin_m,
                        table_margin_m=-settings.table_depth_m)


def registration_cloud(frame: PosedDepth, region: EnvelopeCrop, settings: RefineSettings,
                       depth: DepthFilterSettings | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One keyframe's filtered world points and unit normals in the region, voxel-downsampled (Open3D)."""
    import open3d as o3d

    bare = PosedDepth(frame.arm, frame.frame_id, frame.depth, frame.depth_scale, frame.intrinsics,
                      frame.T_world_cam, None)
    cloud = backproject(bare, depth, region)
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(np.asarray(cloud.points, np.float64))
    pcd.normals = o3d.utility.Vector3dVector(np.asarray(cloud.normals, np.float64))
    down = pcd.voxel_down_sample(settings.voxel_size_m)
    normals = np.asarray(down.normals)
    normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    return np.asarray(down.points), normals


# -- the refinement -----------------------------------------------------------------------------------------
def _measure(T: np.ndarray, centre: np.ndarray) -> dict[str, float]:
    return {"translation_mm": round(displacement_m(T, centre) * 1000.0, 3),
            "rotation_deg": round(rotation_angle_deg(T), 4)}


def _within(T: np.ndarray, centre: np.ndarray, bound_m: float, bound_deg: float) -> str | None:
    """None when ``T`` is within the bounds, else why not (one line)."""
    d, a = displacement_m(T, centre), rotation_angle_deg(T)
    if d > bound_m:
        return f"moves the envelope centre {d * 1000:.2f} mm > bound {bound_m * 1000:.2f} mm"
    if a > bound_deg:
        return f"rotates {a:.3f} deg > bound {bound_deg:.3f} deg"
    return None


def _moved(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    out: np.ndarray = points @ T[:3, :3].T + T[:3, 3]
    return out


def validation_split(views: Sequence[RefineView], fuse_idx: Sequence[int],
                     settings: RefineSettings) -> tuple[list[int], str]:
    """The gate's validation views (indices into ``views``): per arm every ``validate_every``-th of its fuse
    keyframes, starting half a period in; none (and why) when the gate is off or an arm has too few."""
    if settings.validate_every == 0:
        return [], "off (validate_every 0)"
    per_arm: dict[str, list[int]] = {}
    for i in fuse_idx:
        per_arm.setdefault(views[i].arm, []).append(i)
    short = sorted(arm for arm, idx in per_arm.items() if len(idx) < settings.gate_min_views)
    if short or not per_arm:
        return [], (f"not used: {', '.join(short) or 'no arm'} has fewer than {settings.gate_min_views} "
                    "usable fuse keyframes")
    k = settings.validate_every
    return sorted(i for idx in per_arm.values() for i in idx[k // 2::k]), ""


def validation_cost(sources: Sequence[tuple[np.ndarray, np.ndarray]], targets: Sequence[tuple[np.ndarray, np.ndarray]],
                    settings: RefineSettings) -> dict[str, float]:
    """How well the validation views' points (``sources``, world) lie on the fit views' surface
    (``targets``: points and normals, world): the mean point-to-plane distance truncated at
    ``gate_truncate_m`` (a point without a neighbour within ``gate_match_m`` costs the truncation), the median
    matched distance and the matched fraction (mm, mm, fraction)."""
    from scipy.spatial import cKDTree

    tgt = np.concatenate([t[0] for t in targets])
    tgt_n = np.concatenate([t[1] for t in targets])
    src = np.concatenate([p for p, _ in sources])
    dist, idx = cKDTree(tgt).query(src, distance_upper_bound=settings.gate_match_m)
    ok = np.isfinite(dist)
    r = np.abs(np.einsum("ij,ij->i", src[ok] - tgt[idx[ok]], tgt_n[idx[ok]]))
    trunc = settings.gate_truncate_m
    cost = (float(np.sum(np.minimum(r, trunc))) + trunc * float((~ok).sum())) / max(len(src), 1)
    return {"cost_mm": round(cost * 1000, 4), "median_mm": round(float(np.median(r)) * 1000, 4) if r.size else math.nan,
            "matched": round(float(ok.mean()), 4) if len(src) else 0.0}


def refine_poses(views: Sequence[RefineView], frames: Iterable[PosedDepth | None], crop: EnvelopeCrop,
                 uncertainty_m: float | None, settings: RefineSettings | None = None,
                 depth: DepthFilterSettings | None = None) -> RefineResult:
    """Corrected poses of ``views`` (see the module docstring) and the record of every correction.

    ``frames`` yields, in the order of ``views``, the view's depth frame for a ``fuse`` view (None may be
    given for held-out views: they are never read).
    """
    from scipy.spatial import cKDTree

    settings = settings or RefineSettings()
    start = time.perf_counter()
    centre = np.asarray(crop.center_m, np.float64)
    source = "calibration held-out p90 corner error"
    if uncertainty_m is None or not math.isfinite(uncertainty_m) or uncertainty_m <= 0:
        uncertainty_m, source = DEFAULT_UNCERTAINTY_M, "default (the calibration states no held-out error)"
    bound_m = settings.max_sigma * uncertainty_m
    bound_deg = math.degrees(bound_m / settings.lever_m)
    sigma_t = settings.prior_sigma * uncertainty_m
    prior = (sigma_t, sigma_t / settings.lever_m)
    region = registration_region(crop, settings)

    fuse_idx: list[int] = []
    clouds: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    skipped: dict[int, str] = {}
    held_clouds: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for i, (view, frame) in enumerate(zip(views, frames, strict=True)):
        if view.split != "fuse":
            if settings.heldout == "register" and frame is not None:
                held_clouds[i] = registration_cloud(frame, region, settings, depth)
            continue
        if frame is None:
            raise ReconstructionError(f"refinement: no depth frame given for fuse keyframe {view.key}")
        points, normals = registration_cloud(frame, region, settings, depth)
        if len(points) < settings.min_points:
            skipped[i] = f"{len(points)} registration points < {settings.min_points}"
            continue
        fuse_idx.append(i)
        clouds[i] = (points, normals)
    # the gate: some fuse keyframes are left out of the fit and decide whether its corrections are applied
    valid_idx, gate_note = validation_split(views, fuse_idx, settings)
    all_fuse, fuse_idx = fuse_idx, [i for i in fuse_idx if i not in set(valid_idx)]
    arms = sorted({views[i].arm for i in fuse_idx})

    # 1. per arm: the arms' merged clouds aligned to each other, split in half
    arm_T: dict[str, np.ndarray] = {arm: np.eye(4) for arm in arms}
    pair_record: dict[str, Any] | None = None
    if settings.per_arm and len(arms) == 2:
        a, b = arms
        merged = {arm: (np.concatenate([clouds[i][0] for i in fuse_idx if views[i].arm == arm]),
                        np.concatenate([clouds[i][1] for i in fuse_idx if views[i].arm == arm])) for arm in arms}
        # the relative correction of two arms has twice the variance of one arm's
        stride = max(1, len(merged[b][0]) // (4 * settings.max_source_points))
        pair_prior = (prior[0] * math.sqrt(2), prior[1] * math.sqrt(2))
        fit = regularised_icp(merged[b][0][::stride], merged[a][0], merged[a][1], centre, pair_prior, settings,
                              source_normals=merged[b][1][::stride])
        twist = transform_twist(fit.T, centre)
        pair_record = {"source": b, "target": a, "overlap": round(fit.overlap, 4),
                       "rmse_mm": round(fit.rmse_m * 1000, 3), **_measure(fit.T, centre),
                       "rotvec_deg": [round(float(x), 4) for x in np.degrees(twist[:3])],
                       "displacement_mm": [round(float(x), 3) for x in twist[3:] * 1000]}
        if fit.information is not None:  # how many times the prior's information the overlap gives, per direction
            pair_record["information_ratios"] = [round(float(x), 2) for x in information_ratios(fit.information,
                                                                                                pair_prior)]
        if fit.overlap >= settings.min_overlap:
            arm_T[b] = rigid_power(fit.T, 0.5)
            arm_T[a] = np.linalg.inv(arm_T[b])  # the gauge: the arms' corrections cancel
        else:
            pair_record["refused"] = f"overlap {fit.overlap:.3f} < {settings.min_overlap}"

    # 2. per view: each fuse keyframe against all the others (one k-d tree per round), gauge fixed each round
    corr: dict[int, np.ndarray] = {i: arm_T[views[i].arm] for i in fuse_idx}
    rounds: list[dict[str, Any]] = []
    if settings.per_view and len(fuse_idx) >= 3:
        labels = np.concatenate([np.full(len(clouds[i][0]), i) for i in fuse_idx])
        for _ in range(settings.rounds):
            world = np.concatenate([_moved(clouds[i][0], corr[i]) for i in fuse_idx])
            world_n = np.concatenate([clouds[i][1] @ corr[i][:3, :3].T for i in fuse_idx])
            tree = cKDTree(world)
            new, low = {}, 0
            for i in fuse_idx:
                stride = max(1, len(clouds[i][0]) // settings.max_source_points)
                fit = regularised_icp(clouds[i][0][::stride], world, world_n, centre, prior, settings, init=corr[i],
                                      tree=tree, exclude=(labels, i), source_normals=clouds[i][1][::stride])
                if fit.overlap >= settings.min_overlap:
                    new[i] = fit.T
                else:
                    new[i] = corr[i]
                    low += 1
            gauge = np.linalg.inv(mean_transform(list(new.values()), centre))
            step = max(displacement_m(gauge @ new[i] @ np.linalg.inv(corr[i]), centre) for i in fuse_idx)
            corr = {i: gauge @ new[i] for i in fuse_idx}
            rounds.append({"largest_step_mm": round(step * 1000, 3), "low_overlap": low})

    # each arm's mean view correction is the arm's correction; the rest is the view's own
    total_arm: dict[str, np.ndarray] = {}
    arm_record: dict[str, Any] = {}
    for arm in arms:
        own = [corr[i] for i in fuse_idx if views[i].arm == arm]
        total_arm[arm] = mean_transform(own, centre) if own else np.eye(4)
        reason = _within(total_arm[arm], centre, bound_m, bound_deg)
        arm_record[arm] = {**_measure(total_arm[arm], centre), "accepted": reason is None,
                           **({"refused": reason} if reason else {})}
        if reason is not None:
            total_arm[arm] = np.eye(4)

    # the gate: which level (none, arm, arm + view) makes the validation views agree best with the fit views
    level, gate = _gate(views, clouds, fuse_idx, valid_idx, corr, total_arm, arm_record, centre,
                        (bound_m, bound_deg), settings)
    gate = {**gate, "note": gate_note} if gate_note else gate
    if level == "none":
        for arm in arms:
            if arm_record[arm]["accepted"]:
                arm_record[arm].update(accepted=False, refused="validation: no level improved the validation views")
            total_arm[arm] = np.eye(4)

    poses: dict[str, np.ndarray] = {}
    view_rows = []
    counts = {"accepted": 0, "refused": 0, "arm_only": 0, "unchanged": 0}
    for i, view in enumerate(views):
        T_arm = total_arm.get(view.arm, np.eye(4))
        arm_ok = bool(arm_record.get(view.arm, {}).get("accepted", False))
        row: dict[str, Any] = {"key": view.key, "arm": view.arm, "frame_number": view.frame_number,
                               "split": view.split}
        if view.split != "fuse" or i not in corr:
            C = T_arm
            row["applied"] = "arm" if arm_ok else "none"
            if i in skipped:
                row["note"] = skipped[i]
            elif i in valid_idx:
                row["note"] = "validation view: left out of the fit, its arm's correction only"
            counts["arm_only" if arm_ok else "unchanged"] += 1
        elif not arm_ok:
            C = np.eye(4)
            row["applied"] = "none"
            row["refused"] = "its arm's correction was refused"
            counts["refused"] += 1
        else:
            C = corr[i]
            reason = _within(C, centre, bound_m, bound_deg)
            if reason is None and level != "view":
                reason = "validation: the per-view corrections did not improve the validation views"
            row.update({"view_" + k: v for k, v in _measure(C @ np.linalg.inv(T_arm), centre).items()})
            if reason is None:
                row["applied"] = "view"
                counts["accepted"] += 1
            else:
                C = T_arm
                row["applied"] = "arm"
                row["refused"] = reason
                counts["refused"] += 1
        row.update(_measure(C, centre))
        poses[view.key] = C @ np.asarray(view.T_world_cam, np.float64)
        view_rows.append(row)

    if settings.heldout == "register" and held_clouds and all_fuse:
        _register_heldout(views, held_clouds, all_fuse, clouds, poses, view_rows, counts, centre, prior,
                          (bound_m, bound_deg), settings)

    held = ("held-out keyframes get their arm's correction only" if settings.heldout == "arm" else
            "held-out keyframes are then each aligned alone to the refined fuse keyframes (same prior and bounds)")
    record = {
        "method": "regularised point-to-plane ICP: arm-to-arm (split in half), then each fuse keyframe against "
                  f"all others; gauge: mean correction = identity; {held}",
        "heldout": settings.heldout,
        "bound": {"translation_mm": round(bound_m * 1000, 3), "rotation_deg": round(bound_deg, 4),
                  "uncertainty_mm": round(uncertainty_m * 1000, 3), "source": source,
                  "max_sigma": settings.max_sigma, "lever_m": settings.lever_m,
                  "prior_sigma_mm": round(sigma_t * 1000, 3), "measured_at": "the envelope centre"},
        "arm_pair": pair_record, "arms": arm_record, "rounds": rounds, "gate": gate, "counts": counts,
        "views": view_rows, "seconds": round(time.perf_counter() - start, 3),
    }
    return RefineResult(poses=poses, record=record)


def _gate(views: Sequence[RefineView], clouds: dict[int, tuple[np.ndarray, np.ndarray]], fit_idx: list[int],
          valid_idx: list[int], corr: dict[int, np.ndarray], total_arm: dict[str, np.ndarray],
          arm_record: dict[str, Any], centre: np.ndarray, bounds: tuple[float, float],
          settings: RefineSettings) -> tuple[str, dict[str, Any]]:
    """The level to apply (``none``, ``arm`` or ``view``) and its record: each level's validation cost (the
    validation views at their arm's correction against the fit views at that level's); the lowest wins if it
    beats ``none`` by ``gate_min_gain``. No validation views: ``view`` (as without the gate)."""
    if not valid_idx or not fit_idx:
        return "view", {"used": False}

    def arm_T(i: int) -> np.ndarray:
        return total_arm.get(views[i].arm, np.eye(4)) if arm_record.get(views[i].arm, {}).get("accepted") else np.eye(4)

    def view_T(i: int) -> np.ndarray:
        T = corr.get(i)
        return T if T is not None and arm_record[views[i].arm]["accepted"] and _within(T, centre, *bounds) is None \
            else arm_T(i)

    def placed(idx: list[int], how: Any) -> list[tuple[np.ndarray, np.ndarray]]:
        return [(_moved(clouds[i][0], how(i)), clouds[i][1] @ how(i)[:3, :3].T) for i in idx]

    costs = {}
    for level, fit_T, valid_T in (("none", lambda i: np.eye(4), lambda i: np.eye(4)), ("arm", arm_T, arm_T),
                                  ("view", view_T, arm_T)):
        costs[level] = validation_cost(placed(valid_idx, valid_T), placed(fit_idx, fit_T), settings)
    best = min(costs, key=lambda k: costs[k]["cost_mm"])  # ties: the first, i.e. the least correction
    gain = 1.0 - costs[best]["cost_mm"] / max(costs["none"]["cost_mm"], 1e-12)
    chosen = best if gain >= settings.gate_min_gain else "none"
    return chosen, {"used": True, "validation_views": [views[i].key for i in valid_idx], "costs": costs,
                    "gain": round(gain, 4), "min_gain": settings.gate_min_gain, "applied": chosen,
                    **({"refused": f"best level {best} lowers the validation cost by {100 * gain:.1f} % < "
                                   f"{100 * settings.gate_min_gain:.0f} %"} if chosen != best else {})}


def _register_heldout(views: Sequence[RefineView], held_clouds: dict[int, tuple[np.ndarray, np.ndarray]],
                      fuse_idx: list[int], clouds: dict[int, tuple[np.ndarray, np.ndarray]],
                      poses: dict[str, np.ndarray], rows: list[dict[str, Any]], counts: dict[str, int],
                      centre: np.ndarray, prior: tuple[float, float], bounds: tuple[float, float],
                      settings: RefineSettings) -> None:
    """``heldout: register``: each held-out keyframe aligned alone to the fuse keyframes at their refined
    poses (which never saw it), starting from its arm's correction, with the same prior and bounds."""
    from scipy.spatial import cKDTree

    def correction(i: int) -> np.ndarray:
        out: np.ndarray = poses[views[i].key] @ np.linalg.inv(np.asarray(views[i].T_world_cam, np.float64))
        return out

    world = np.concatenate([_moved(clouds[i][0], correction(i)) for i in fuse_idx])
    world_n = np.concatenate([clouds[i][1] @ correction(i)[:3, :3].T for i in fuse_idx])
    tree = cKDTree(world)
    for i, (points, normals) in held_clouds.items():
        row = rows[i]
        if len(points) < settings.min_points:
            row["note"] = f"{len(points)} registration points < {settings.min_points}: not registered"
            continue
        start = correction(i)
        stride = max(1, len(points) // settings.max_source_points)
        fit = regularised_icp(points[::stride], world, world_n, centre, prior, settings, init=start, tree=tree,
                              source_normals=normals[::stride])
        reason = _within(fit.T, centre, *bounds)
        if fit.overlap < settings.min_overlap:
            reason = f"overlap {fit.overlap:.3f} < {settings.min_overlap}"
        row["registered_" + "translation_mm"] = _measure(fit.T, centre)["translation_mm"]
        if reason is not None:
            row["refused"] = reason
            continue
        counts["arm_only" if row["applied"] == "arm" else "unchanged"] -= 1
        counts["accepted"] += 1
        row["applied"] = "registered"
        row.update(_measure(fit.T, centre))
        poses[views[i].key] = fit.T @ np.asarray(views[i].T_world_cam, np.float64)


__all__ = ["DEFAULT_UNCERTAINTY_M", "RefineResult", "RefineSettings", "RefineView", "refine_poses",
           "registration_cloud",
           "registration_region", "validation_cost", "validation_split"]
