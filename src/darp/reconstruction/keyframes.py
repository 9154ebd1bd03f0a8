"""Keyframe selection: settled, view-diverse frames per arm, and a deterministic held-out split.

A survey records both cameras continuously (about 3,000 depth frames per camera in the paper), but
most frames are redundant or taken while the arm moves. Keyframes are chosen per arm from the pose
recovery (:func:`darp.reconstruction.poses.recover_survey_poses`) in four steps:

1. **Settled**: the frame has a pose, its own arm's largest joint speed is at most the arm's
   *stillness threshold*, and the arm has been still for at least ``settle_s`` (a settled window after
   a move: the time since the first still frame of the run). The other arm does not matter: it does not
   move this camera. The threshold comes from the survey's own joint log: the encoder noise of every
   joint is measured robustly from the log's second differences (:func:`joint_speed_noise`: the median
   absolute deviation ignores moves), and the threshold is ``noise_factor`` times the resulting speed
   noise of one joint, never below ``max_joint_speed_rad_s`` (the floor for a clean log) and never above
   ``max_still_speed_rad_s`` (slower than any move). A fixed threshold broke on a noisier rig: with
   0.02 deg encoder noise a still arm reads ~0.035 rad/s, above the old fixed 0.02 rad/s.
2. **In view**: the object centre (envelope centre) projects into the depth image, in front of the
   camera, at least ``view_margin_px`` inside the border.
3. **Views**: consecutive settled frames form a *view* (a dwell), split where the viewing direction
   drifts more than ``view_split_deg`` from the view's first frame or the frames stop being consecutive.
4. **Diverse views**: up to ``per_view`` frames spread evenly over each view are its keyframe
   candidates. Views are considered nearest first (mean camera distance to the object centre: depth
   noise grows with the square of the distance, so of two views from one direction the closer one
   wins; then the longer dwell, then the earlier), and a view is taken only when every one of its
   frames is at least ``min_separation_deg`` from every keyframe of the views already taken. With
   ``max_views``, the most diverse of those views are kept (farthest-point sampling).

Only the survey's own views: frames at the arm's **park pose** (every joint within
``park_tolerance_rad`` of the envelope's ``park_q_rad``, when the survey records one) are never
candidates, and a view more than ``max_view_distance_ratio`` times farther from the object centre
than the arm's nearest view is dropped. A parked camera often still sees the object, from about twice
the survey's standoff (0.77 m against 0.37 m on the twin): such keyframes had the worst depth
agreement and the near-empty completion partials (issue 31), and the distance rule also catches a far
dwell in a survey that records no park pose (the DARP release's envelopes do not).

The viewing direction of a frame is the unit vector from the object centre to the camera centre
(direction bins about the envelope centre). Without an envelope centre, the point closest to all
settled optical axes (least squares) is used.

**Held-out split**: per arm, in time order, keyframe ``i`` is held out when
``i % heldout_every == heldout_offset`` (default every 5th: 20 %, about 22 keyframes for a survey
of 10 views per arm with 3 frames each, the paper's 224 over ten objects). With ``heldout_unit:
view`` the rule counts views instead and holds out every keyframe of the chosen views, so that no fused
keyframe shares a held-out keyframe's pose. The rule depends only on the selection, so it is
reproducible and independent of any random seed.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from darp.errors import ReconstructionError
from darp.formats.realsense.types import Intrinsics
from darp.formats.schema import dataclass_from_mapping

FUSE, HELDOUT = "fuse", "heldout"
HELDOUT_UNITS = ("keyframe", "view")


@dataclass(frozen=True)
class KeyframeSettings:
    """Every keyframe-selection parameter (see the module docstring and docs/processing-pipeline.md)."""

    max_joint_speed_rad_s: float = 0.02  # stillness floor: a still Z1 logs ~0.005 rad/s of encoder noise
    noise_factor: float = 4.0  # stillness threshold: this many times the log's measured speed noise (0: off)
    max_still_speed_rad_s: float = 0.25  # ... but never above this (a move is ~0.3-0.6 rad/s)
    min_keyframes: int = 3  # per arm: fewer is flagged as implausible in results.json and the report
    settle_s: float = 0.25  # the arm must have been still this long (a settled window after a move)
    view_split_deg: float = 2.0  # a still run drifting more than this from its first frame is split
    min_separation_deg: float = 6.0  # keyframes of different views are at least this far apart
    per_view: int = 3  # keyframes per view (dwell), spread evenly over its settled frames
    max_views: int | None = None  # per arm; None: every view that is far enough from the others
    view_margin_px: float = 0.0  # the object centre must project this far inside the image
    max_view_distance_ratio: float | None = 2.0  # drop views this many times farther than the nearest (None: off)
    park_tolerance_rad: float = 0.05  # a frame with every joint this close to the park pose is never a keyframe
    heldout_every: int = 5  # held-out split: every n-th keyframe per arm (20 %) ...
    heldout_offset: int = 2  # ... starting with this one
    heldout_unit: str = "keyframe"  # or "view": every n-th view held out whole (all its keyframes)

    def __post_init__(self) -> None:
        if not self.max_joint_speed_rad_s > 0:
            raise ReconstructionError(f"max_joint_speed_rad_s must be > 0, got {self.max_joint_speed_rad_s}")
        if not (self.noise_factor >= 0 and self.max_still_speed_rad_s >= self.max_joint_speed_rad_s):
            raise ReconstructionError("noise_factor must be >= 0 and max_still_speed_rad_s >= max_joint_speed_rad_s")
        if self.min_keyframes < 0:
            raise ReconstructionError(f"min_keyframes must be >= 0, got {self.min_keyframes}")
        if self.settle_s < 0 or self.view_split_deg <= 0 or self.min_separation_deg < 0:
            raise ReconstructionError("settle_s and min_separation_deg must be >= 0 and view_split_deg > 0")
        if self.per_view < 1 or (self.max_views is not None and self.max_views < 1):
            raise ReconstructionError("per_view and max_views must be >= 1")
        if self.heldout_every < 2 or not 0 <= self.heldout_offset < self.heldout_every:
            raise ReconstructionError(
                f"held-out split needs heldout_every >= 2 and 0 <= heldout_offset < heldout_every, "
                f"got {self.heldout_every}, {self.heldout_offset}")
        if self.max_view_distance_ratio is not None and not self.max_view_distance_ratio >= 1:
            raise ReconstructionError(
                f"max_view_distance_ratio must be >= 1 or None, got {self.max_view_distance_ratio}")
        if not self.park_tolerance_rad >= 0:
            raise ReconstructionError(f"park_tolerance_rad must be >= 0, got {self.park_tolerance_rad}")
        if self.heldout_unit not in HELDOUT_UNITS:
            raise ReconstructionError(
                f"heldout_unit must be one of {', '.join(HELDOUT_UNITS)}, got {self.heldout_unit!r}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def still_threshold(self, speed_noise_rad_s: float = 0.0) -> float:
        """The stillness threshold (rad/s) for a log whose one-joint speed noise is ``speed_noise_rad_s``."""
        noise = float(speed_noise_rad_s) if math.isfinite(speed_noise_rad_s) else 0.0
        return min(max(self.max_joint_speed_rad_s, self.noise_factor * noise), self.max_still_speed_rad_s)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> KeyframeSettings:
        return dataclass_from_mapping(cls, values, "keyframes", error=ReconstructionError)


@dataclass(frozen=True, eq=False)
class ArmKeyframes:
    """The keyframes of one arm: indices into that arm's trajectory, in time order."""

    arm: str
    indices: np.ndarray  # (K,) int64 positions in the arm's frame list (time order)
    view_ids: np.ndarray  # (K,) int64 view (dwell) each keyframe comes from
    heldout: np.ndarray  # (K,) bool: held out of fusion for evaluation
    directions: np.ndarray  # (K, 3) unit viewing directions (object centre -> camera)
    counts: dict[str, int] = field(default_factory=dict)  # frames, posed, settled, in_view, views ...
    still_threshold_rad_s: float = 0.02  # the stillness threshold used (module docstring, step 1)
    speed_noise_rad_s: float = 0.0  # the joint log's measured one-joint speed noise

    def __len__(self) -> int:
        return int(self.indices.size)

    @property
    def splits(self) -> list[str]:
        return [HELDOUT if h else FUSE for h in self.heldout]


# -- building blocks -------------------------------------------------------------------------------
def joint_speed_noise(log_t_s: np.ndarray, log_q_rad: np.ndarray) -> float:
    """The speed noise (rad/s, one standard deviation) of one joint's velocity between consecutive log rows.

    Encoder noise of std ``s`` makes a second difference ``q[i+1] - 2 q[i] + q[i-1]`` noise of std
    ``sqrt(6) s``; moves at constant speed add nothing to it and accelerations only in a minority of
    rows, so the median absolute deviation (x 1.4826) measures ``s`` even in a log that moves most of
    the time. The velocity between two rows ``dt`` apart then has noise ``sqrt(2) s / dt``; the
    noisiest joint and the median row spacing are used. 0 for a log of fewer than 5 rows.
    """
    t = np.asarray(log_t_s, np.float64).reshape(-1)
    q = np.asarray(log_q_rad, np.float64).reshape(t.size, -1)
    finite = np.isfinite(t) & np.all(np.isfinite(q), axis=1)
    t, q = t[finite], q[finite]
    if t.size < 5:
        return 0.0
    dt = np.diff(t)
    dt = dt[dt > 0]
    if dt.size == 0:
        return 0.0
    d2 = q[2:] - 2.0 * q[1:-1] + q[:-2]
    mad = np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0)
    sigma_q = 1.4826 * mad / math.sqrt(6.0)
    return float(math.sqrt(2.0) * float(np.max(sigma_q)) / float(np.median(dt)))


def settled_mask(t_s: np.ndarray, joint_speed_rad_s: np.ndarray, settings: KeyframeSettings,
                 threshold_rad_s: float | None = None) -> np.ndarray:
    """Boolean (N,): frames whose arm is slow and has been still for ``settle_s`` (frames in time order).

    ``threshold_rad_s``: the stillness threshold (default ``settings.max_joint_speed_rad_s``; callers
    with a joint log pass ``settings.still_threshold(joint_speed_noise(...))``). A NaN speed (a frame
    without a pose) counts as moving: it breaks the still run.
    """
    t = np.asarray(t_s, np.float64)
    speed = np.asarray(joint_speed_rad_s, np.float64)
    if t.shape != speed.shape or t.ndim != 1:
        raise ReconstructionError(f"times {t.shape} and speeds {speed.shape} must be equal 1-D arrays")
    if t.size > 1 and np.any(np.diff(t) < 0):
        raise ReconstructionError("frame times must be in time order")
    limit = settings.max_joint_speed_rad_s if threshold_rad_s is None else float(threshold_rad_s)
    still = np.isfinite(speed) & (speed <= limit)
    # start time of the still run each frame belongs to: a run starts at a still frame after a non-still one
    starts = still & ~np.concatenate(([False], still[:-1]))
    run_start = np.where(starts, t, -np.inf)
    run_start = np.maximum.accumulate(run_start) if t.size else run_start
    return still & (t - run_start >= settings.settle_s - 1e-9)


def viewing_directions(T_world_cam: np.ndarray, centre_m: np.ndarray) -> np.ndarray:
    """(N, 3) unit vectors from ``centre_m`` to each camera centre (NaN for unposed frames)."""
    c = np.asarray(T_world_cam, np.float64)[:, :3, 3] - np.asarray(centre_m, np.float64)
    length = np.linalg.norm(c, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return c / np.where(length > 0, length, np.nan)


def centre_in_view(T_world_cam: np.ndarray, centre_m: np.ndarray, intrinsics: Intrinsics,
                   margin_px: float = 0.0) -> np.ndarray:
    """Boolean (N,): the centre lies in front of the camera and projects inside the image (pinhole)."""
    T = np.asarray(T_world_cam, np.float64)
    rel = np.asarray(centre_m, np.float64) - T[:, :3, 3]
    cam = np.einsum("nji,nj->ni", T[:, :3, :3], rel)  # R^T (c - t)
    z = cam[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        u = intrinsics.fx * cam[:, 0] / z + intrinsics.ppx
        v = intrinsics.fy * cam[:, 1] / z + intrinsics.ppy
        inside: np.ndarray = ((z > 0) & (u >= -0.5 + margin_px) & (u <= intrinsics.width - 0.5 - margin_px)
                              & (v >= -0.5 + margin_px) & (v <= intrinsics.height - 0.5 - margin_px))
        return inside


def look_at_point(T_world_cam: np.ndarray) -> np.ndarray:
    """The point closest (least squares) to the optical axes (camera +z) of the given poses."""
    T = np.asarray(T_world_cam, np.float64)
    T = T[np.all(np.isfinite(T.reshape(len(T), -1)), axis=1)]
    if len(T) < 2:
        raise ReconstructionError("need at least two posed frames to find where the cameras look")
    origins, axes = T[:, :3, 3], T[:, :3, 2]
    projector = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]  # I - a a^T per axis
    A, b = projector.sum(axis=0), np.einsum("nij,nj->i", projector, origins)
    if np.linalg.cond(A) > 1e8:
        raise ReconstructionError("the optical axes are parallel: cannot find where the cameras look")
    return np.linalg.solve(A, b)


def split_views(candidate: np.ndarray, directions: np.ndarray, view_split_deg: float) -> np.ndarray:
    """View id per frame (-1 for non-candidates): runs of consecutive candidates, split on direction drift."""
    ids = np.full(candidate.shape[0], -1, np.int64)
    cos_split = np.cos(np.radians(view_split_deg))
    view, anchor = -1, None
    for i in np.flatnonzero(candidate):
        if anchor is None or i == 0 or not candidate[i - 1] or float(directions[i] @ directions[anchor]) < cos_split:
            view, anchor = view + 1, i
        ids[i] = view
    return ids


def spread(indices: np.ndarray, k: int) -> np.ndarray:
    """Up to ``k`` of ``indices`` spread evenly from the first to the last (the middle one for k = 1)."""
    n = indices.size
    if n <= k:
        return indices
    if k == 1:
        return indices[[n // 2]]
    return indices[np.unique(np.rint(np.linspace(0, n - 1, k)).astype(np.int64))]


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    angles: np.ndarray = np.degrees(np.arccos(np.clip(a @ b.T, -1.0, 1.0)))
    return angles


# -- selection ---------------------------------------------------------------------------------------
def select_arm_keyframes(arm: str, t_s: np.ndarray, T_world_cam: np.ndarray, joint_speed_rad_s: np.ndarray,
                         centre_m: np.ndarray | None, settings: KeyframeSettings | None = None,
                         intrinsics: Intrinsics | None = None, speed_noise_rad_s: float = 0.0,
                         q_rad: np.ndarray | None = None, park_q_rad: np.ndarray | None = None) -> ArmKeyframes:
    """Keyframes of one arm's frames (in time order): settled, in view, diverse, split (module docstring).

    ``centre_m`` is the object (envelope) centre, or None to use where the settled cameras look.
    Without ``intrinsics`` the in-view test is skipped. ``speed_noise_rad_s``: the joint log's measured
    speed noise (:func:`joint_speed_noise`), which sets the stillness threshold. ``q_rad`` (N, 6) and
    ``park_q_rad`` (6,): each frame's joints and the arm's park pose; frames at park are never keyframes.
    """
    settings = settings or KeyframeSettings()
    threshold = settings.still_threshold(speed_noise_rad_s)
    T = np.asarray(T_world_cam, np.float64)
    n = T.shape[0]
    if T.shape != (n, 4, 4):
        raise ReconstructionError(f"{arm}: poses must be (N, 4, 4), got {T.shape}")
    posed = np.all(np.isfinite(T.reshape(n, 16)), axis=1)
    settled = settled_mask(t_s, joint_speed_rad_s, settings, threshold) & posed
    parked = at_park(q_rad, park_q_rad, settings.park_tolerance_rad, n)
    if centre_m is None:
        centre = look_at_point(T[settled]) if settled.sum() >= 2 else None
    else:
        centre = np.asarray(centre_m, np.float64).reshape(3)
    counts = {"frames": n, "posed": int(posed.sum()), "settled": int(settled.sum()),
              "at_park": int((settled & parked).sum())}
    noise = {"still_threshold_rad_s": threshold, "speed_noise_rad_s": float(speed_noise_rad_s)}
    if centre is None:
        return _empty(arm, {**counts, "in_view": 0, "views_found": 0, "views": 0}, **noise)
    directions = np.zeros((n, 3))
    directions[posed] = viewing_directions(T[posed], centre)
    candidate = settled & ~parked & np.all(np.isfinite(directions), axis=1)
    if intrinsics is not None:
        candidate[posed] &= centre_in_view(T[posed], centre, intrinsics, settings.view_margin_px)
    counts["in_view"] = int(candidate.sum())
    view_of = split_views(candidate, directions, settings.view_split_deg)
    n_views = int(view_of.max()) + 1 if candidate.any() else 0
    counts["views_found"] = n_views
    if n_views == 0:
        return _empty(arm, {**counts, "views": 0}, **noise)

    members = [spread(np.flatnonzero(view_of == v), settings.per_view) for v in range(n_views)]
    offsets = T[:, :3, 3] - centre
    distance = np.array([np.linalg.norm(offsets[m], axis=1).mean() for m in members])
    near = _near_views(distance, settings.max_view_distance_ratio)
    counts["far_views"] = int(n_views - near.sum())
    taken = _diverse_views(members, view_of, directions, distance, near, settings)
    counts["views"] = len(taken)
    indices = np.sort(np.concatenate([members[v] for v in taken]))
    heldout = heldout_split(view_of[indices], settings)
    counts["keyframes"] = int(indices.size)
    counts["heldout"] = int(heldout.sum())
    return ArmKeyframes(arm=arm, indices=indices, view_ids=view_of[indices], heldout=heldout,
                        directions=directions[indices], counts=counts, **noise)


def heldout_split(view_ids: np.ndarray, settings: KeyframeSettings) -> np.ndarray:
    """Held-out mask of one arm's keyframes in time order (``view_ids``: each keyframe's view).

    ``keyframe``: every ``heldout_every``-th keyframe. ``view``: every ``heldout_every``-th view in order of
    first appearance, all of its keyframes: a held-out frame then has no fused frame from its own pose, so the
    held-out figures measure how the views disagree, not how one dwell's frames repeat."""
    if settings.heldout_unit == "keyframe":
        rank = np.arange(view_ids.size)
    else:
        _, first, rank = np.unique(view_ids, return_index=True, return_inverse=True)
        rank = np.argsort(np.argsort(first))[rank]  # views numbered in time order
    held: np.ndarray = (rank % settings.heldout_every) == settings.heldout_offset
    return held


def at_park(q_rad: np.ndarray | None, park_q_rad: np.ndarray | None, tolerance_rad: float, n: int) -> np.ndarray:
    """Boolean (N,): frames whose every joint is within ``tolerance_rad`` of the park pose (none without one)."""
    if q_rad is None or park_q_rad is None:
        return np.zeros(n, bool)
    q = np.asarray(q_rad, np.float64).reshape(n, -1)
    park = np.asarray(park_q_rad, np.float64).reshape(-1)
    if q.shape[1] != park.size:
        raise ReconstructionError(f"joints {q.shape} and park pose {park.shape} differ in length")
    with np.errstate(invalid="ignore"):
        parked: np.ndarray = np.all(np.abs(q - park) <= tolerance_rad, axis=1)
    return parked


def _near_views(distance: np.ndarray, ratio: float | None) -> np.ndarray:
    """Boolean (V,): views at most ``ratio`` times as far from the object as the nearest (all with None)."""
    if ratio is None or distance.size == 0:
        return np.ones(distance.size, bool)
    near: np.ndarray = distance <= ratio * float(distance.min()) + 1e-9
    return near


def _diverse_views(members: list[np.ndarray], view_of: np.ndarray, directions: np.ndarray,
                   distance: np.ndarray, near: np.ndarray, settings: KeyframeSettings) -> list[int]:
    """Views taken nearest first (then longest, then earliest) when ``near`` and far enough in direction
    from those taken; with ``max_views``, the most diverse of them by farthest-point sampling (the nearest
    view first)."""
    n_views = len(members)
    length = np.bincount(view_of[view_of >= 0], minlength=n_views)
    order = sorted((v for v in range(n_views) if near[v]),
                   key=lambda v: (round(float(distance[v]), 3), -int(length[v]), v))
    taken: list[int] = []
    chosen = np.empty((0, 3))
    for v in order:
        if taken and _angles_deg(directions[members[v]], chosen).min() < settings.min_separation_deg:
            continue
        taken.append(v)
        chosen = np.vstack([chosen, directions[members[v]]])
    if settings.max_views is None or len(taken) <= settings.max_views:
        return taken
    kept, rest = [taken[0]], taken[1:]
    while len(kept) < settings.max_views:
        kept_dirs = np.vstack([directions[members[v]] for v in kept])
        seps = [float(_angles_deg(directions[members[v]], kept_dirs).min()) for v in rest]
        kept.append(rest.pop(int(np.argmax(seps))))
    return kept


def _empty(arm: str, counts: dict[str, int], still_threshold_rad_s: float = 0.02,
           speed_noise_rad_s: float = 0.0) -> ArmKeyframes:
    return ArmKeyframes(arm, np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, bool), np.empty((0, 3)),
                        {**counts, "keyframes": 0, "heldout": 0}, still_threshold_rad_s, speed_noise_rad_s)


def select_survey_keyframes(trajectories: Mapping[str, Any], centre_m: np.ndarray | None,
                            settings: KeyframeSettings | None = None,
                            intrinsics: Mapping[str, Intrinsics | None] | None = None,
                            park_q_rad: Mapping[str, Any] | None = None) -> dict[str, ArmKeyframes]:
    """Keyframes of every arm of a pose recovery (``SurveyPoses.trajectories``: CameraTrajectory by arm).

    Frames are taken in timestamp order; ``intrinsics`` (depth stream, by arm) enable the in-view test
    (an arm without them, missing or None, gets none). A trajectory's ``speed_noise_rad_s`` (measured
    from the joint log by :func:`darp.reconstruction.poses.recover_survey_poses`) sets its arm's
    stillness threshold. ``park_q_rad`` (by arm: the envelope's park poses) keeps keyframes off the park pose.
    """
    out: dict[str, ArmKeyframes] = {}
    for arm, traj in trajectories.items():
        order = np.argsort(traj.timestamps_ms, kind="stable")
        poses = traj.poses
        park = None if park_q_rad is None else park_q_rad.get(arm)
        picked = select_arm_keyframes(
            arm, poses.t_s[order], poses.T_world_cam[order], poses.joint_speed_rad_s[order], centre_m, settings,
            None if intrinsics is None else intrinsics.get(arm), float(getattr(traj, "speed_noise_rad_s", 0.0)),
            None if park is None else poses.q_rad[order], None if park is None else np.asarray(park, np.float64))
        out[arm] = ArmKeyframes(arm, order[picked.indices], picked.view_ids, picked.heldout, picked.directions,
                                picked.counts, picked.still_threshold_rad_s, picked.speed_noise_rad_s)
    return out


__all__ = [
    "FUSE",
    "HELDOUT",
    "ArmKeyframes",
    "KeyframeSettings",
    "at_park",
    "centre_in_view",
    "joint_speed_noise",
    "look_at_point",
    "select_arm_keyframes",
    "select_survey_keyframes",
    "settled_mask",
    "split_views",
    "spread",
    "viewing_directions",
]
