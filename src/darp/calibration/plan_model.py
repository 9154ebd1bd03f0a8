"""Extra capture poses where the richer model is poorly determined: greedy D-optimal selection.

Given the captures taken (their observations and the calibration solved from them) and candidate
joint configurations per arm (e.g. :func:`darp.calibration.plan.plan_captures`' feasible poses),
each candidate's board corners are predicted through the current calibration and its contribution
``J_c^T J_c`` to the information matrix of every unknown is computed (the same analytic Jacobian as
the solve, with every kinematic candidate of the model free and the priors of
:data:`darp.calibration.refine.KIN_PRIOR_STD`). The candidate that most increases
``log det`` of the kinematic parameters' information (the Schur complement over the hand-eyes,
bases, board and joint zeros, which are nuisance here) is added, and so on: the greedy D-optimal
design that most shrinks the joint covariance of the poorly determined combinations.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from darp.calibration.board import corners_board_m
from darp.calibration.captures import CaptureSet
from darp.calibration.detect import DetectionSettings, detect_captures
from darp.calibration.jacobian import residuals_and_jacobian
from darp.calibration.kinematic_ident import MODEL_CANDIDATES
from darp.calibration.model import ChainParams, Observations, board_in_stream, build_observations
from darp.calibration.plan import CapturePlan, PlannedPose, PlanSettings, _order, plan_captures
from darp.calibration.refine import Layout
from darp.calibration.solve import calibrate_observations
from darp.calibration.world_frame import world_from_reference
from darp.errors import CalibrationError
from darp.formats.calibration import CharucoBoardSpec
from darp.kinematics.rig import Rig
from darp.kinematics.transforms import invert_transform


def candidate_observations(params: ChainParams, obs: Observations, board: CharucoBoardSpec,
                           candidates: dict[str, np.ndarray], min_corners: int = 12
                           ) -> tuple[Observations, list[tuple[str, int]]]:
    """Predicted (noise-free) observations of candidate configurations; returns them and (arm, index) per capture."""
    P = corners_board_m(board)
    rows = []
    for arm, Q in candidates.items():
        ref = int(np.flatnonzero(obs.for_arm(arm))[0])
        rows += [(arm, k, ref, q) for k, q in enumerate(np.atleast_2d(Q))]
    if not rows:
        raise CalibrationError("no candidate poses to choose from")
    stub = Observations(arms=obs.arms, capture_ids=[f"{a}_cand{k}" for a, k, _, _ in rows],
                        arm_index=np.array([obs.arms.index(a) for a, _, _, _ in rows]),
                        q_rad=np.array([q for _, _, _, q in rows]),
                        T_stream_depth=obs.T_stream_depth[[r for _, _, r, _ in rows]],
                        K=obs.K[[r for _, _, r, _ in rows]], corner_capture=np.zeros(0, int),
                        corner_id=np.zeros(0, int), P_board=np.zeros((0, 3)), uv=np.zeros((0, 2)),
                        T_depth_board_pnp=np.tile(np.eye(4), (len(rows), 1, 1)))
    T = board_in_stream(params, stub)
    caps: list[np.ndarray] = []
    ids: list[np.ndarray] = []
    uvs: list[np.ndarray] = []
    keep_rows: list[int] = []
    for i in range(len(rows)):
        Pc = P @ T[i, :3, :3].T + T[i, :3, 3]
        K = stub.K[i]
        z = np.maximum(Pc[:, 2], 1e-6)
        uv = np.stack([K[0, 0] * Pc[:, 0] / z + K[0, 2], K[1, 1] * Pc[:, 1] / z + K[1, 2]], axis=1)
        w, h = 2 * K[0, 2], 2 * K[1, 2]
        inside = (Pc[:, 2] > 0.05) & (uv[:, 0] > 5) & (uv[:, 0] < w - 6) & (uv[:, 1] > 5) & (uv[:, 1] < h - 6)
        if np.count_nonzero(inside) >= min_corners:
            caps.append(np.full(np.count_nonzero(inside), len(keep_rows)))
            ids.append(np.flatnonzero(inside))
            uvs.append(uv[inside])
            keep_rows.append(i)
    if not keep_rows:
        raise CalibrationError("no candidate pose sees the board")
    sel = np.array(keep_rows)
    out = Observations(arms=obs.arms, capture_ids=[stub.capture_ids[i] for i in sel], arm_index=stub.arm_index[sel],
                       q_rad=stub.q_rad[sel], T_stream_depth=stub.T_stream_depth[sel], K=stub.K[sel],
                       corner_capture=np.concatenate(caps), corner_id=np.concatenate(ids),
                       P_board=P[np.concatenate(ids)], uv=np.concatenate(uvs),
                       T_depth_board_pnp=stub.T_depth_board_pnp[sel])
    return out, [(rows[i][0], rows[i][1]) for i in sel]


def _information(layout: Layout, params: ChainParams, obs: Observations,
                 sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-capture information matrices (M, n, n) of ``obs`` under ``layout``."""
    _, J = residuals_and_jacobian(np.zeros(layout.size), layout, params, obs, sigma_px)
    row_capture = np.repeat(obs.corner_capture, 2)
    info = np.zeros((obs.n_captures, layout.size, layout.size))
    for c in range(obs.n_captures):
        Jc = J[row_capture == c]
        info[c] = Jc.T @ Jc
    return info, J


def _kin_logdet(A: np.ndarray, kin: np.ndarray, other: np.ndarray) -> float:
    S = A[np.ix_(kin, kin)] - A[np.ix_(kin, other)] @ np.linalg.solve(A[np.ix_(other, other)], A[np.ix_(other, kin)])
    sign, logdet = np.linalg.slogdet(0.5 * (S + S.T))
    return float(logdet) if sign > 0 else -np.inf


def select_extra_poses(params: ChainParams, obs: Observations, board: CharucoBoardSpec,
                       candidates: dict[str, np.ndarray], free_joints: dict[str, np.ndarray], n_extra: int,
                       model: str = "kinematic+compliance", sigma_px: float = 0.5) -> list[tuple[str, int]]:
    """The ``n_extra`` candidates, in order, that most increase the kinematic parameters' information."""
    cand_obs, ids = candidate_observations(params, obs, board, candidates)
    mask = MODEL_CANDIDATES[model]
    layout = Layout(obs.arms, {a: np.asarray(free_joints[a], bool) for a in obs.arms},
                    free_kin={a: mask.copy() for a in obs.arms})
    _, J0 = residuals_and_jacobian(np.zeros(layout.size), layout, params, obs, sigma_px)
    A = J0.T @ J0
    kin = layout.kin_columns()
    A[kin, kin] += 1.0 / layout.kin_prior() ** 2
    other = np.setdiff1d(np.arange(layout.size), kin)
    A[other, other] += 1e-9 * np.maximum(np.diag(A)[other], 1e-12)  # gauge safety
    info, _ = _information(layout, params, cand_obs, sigma_px)
    chosen: list[int] = []
    for _ in range(min(n_extra, len(ids))):
        scores = np.array([-np.inf if c in chosen else _kin_logdet(A + info[c], kin, other) for c in range(len(ids))])
        best = int(np.argmax(scores))
        chosen.append(best)
        A = A + info[best]
    return [ids[c] for c in chosen]


def extend_plan(captures: CaptureSet, rig: Rig, n_per_arm: int, *, model: str = "kinematic+compliance",
                n_candidates: int = 300, seed: int = 0) -> tuple[CapturePlan, dict[str, Any]]:
    """A capture plan of ``n_per_arm`` extra poses per arm for ``captures`` (already taken): the captures are
    solved with ``model``, feasible candidate poses planned on the nominal ``rig`` around the board the solve
    found, and the extra poses chosen by :func:`select_extra_poses`. Returns the plan and a summary."""
    detections = detect_captures(captures, DetectionSettings())
    arms = tuple(sorted(captures.arms))
    obs = build_observations(detections, captures.board, arms)
    core = calibrate_observations(obs, model=model)
    assert core.identifiability is not None
    T_ref_world = world_from_reference(core.params.T_ref_base, core.params.T_ref_board, arms)
    T_world_board = invert_transform(T_ref_world) @ core.params.T_ref_board
    s = PlanSettings(n_per_arm=min(60, n_candidates), n_candidates=n_candidates)
    pool = plan_captures(rig, captures.board, T_world_board, settings=s, seed=seed, arms=arms)
    chosen: dict[str, list[PlannedPose]] = {}
    for arm in arms:  # each arm its own quota (the arms share only the board and the base-to-base)
        candidates = {arm: np.array([p.q_rad for p in pool.poses[arm]])}
        picks = select_extra_poses(core.params, obs, captures.board, candidates, core.identifiability.identifiable,
                                   n_per_arm, model, core.refined.sigma_px)
        chosen[arm] = [pool.poses[arm][k] for _, k in picks]
    rejected: dict[str, dict[str, int]] = {a: {} for a in arms}
    poses = {a: _order(rig, a, chosen[a], s, rejected[a]) for a in arms}
    plan = CapturePlan(board=captures.board, T_world_board=T_world_board, seed=seed, settings=s, poses=poses,
                       rejected=rejected)
    summary = {"model": model, "captures": obs.n_captures, "candidates": {a: len(pool.poses[a]) for a in arms},
               "chosen": {a: len(v) for a, v in poses.items()}}
    return plan, summary


__all__ = ["candidate_observations", "extend_plan", "select_extra_poses"]
