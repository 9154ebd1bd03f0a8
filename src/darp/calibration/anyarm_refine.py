"""darp's any-arm hand-eye refinement: boards placed together in the base, PnP-weighted, with a flange-sag term.

Each capture ``i`` (arm ``a``) places the board in the reference frame by itself,
``T_i = T_ref_base_a S_a(F_i) F_i X_a T_cam_board_i``; the refinement moves the board ``W``, the other
bases, the hand-eyes ``X_a`` and the sag terms ``S_a`` until those boards agree:

- **centre** residual: the distance (mm) of the board's centre placed by ``T_i`` from ``W``'s;
- **rotation** residual: ``log(W^-1 T_i)`` (rad) times a lever (mm/rad), whitened per capture by the rotation
  uncertainty of that capture's own board pose. A single-image board pose is much less certain in its tilt
  (rotation about axes in the board plane) than in its in-plane rotation, and more so far away and head-on:
  the covariance is PnP's (``(J^T J)^-1`` of the board corners' pixels, isotropic pixel noise), mixed with an
  isotropic floor (``beta``: its share) for the arm's own rotation errors, and normalised to a median of 1.
  How much of a set's rotation noise is PnP's differs (a real camera's tilt noise vs an arm's own rotation
  errors), so by default each share in ``BETAS`` is fitted and the one whose noise model gives the fit's
  rotation residuals the highest likelihood (:func:`rotation_nll`) is kept. Measured (5-fold, fold seeds 0..2):
  twin seed 3 chooses 0 (isotropic) and its held-out rotation max drops from 0.608 to 0.466 deg; Doosan chooses
  0.99, the twins seeds 7 and 11 0.9-0.99, with every figure within 1 %;
- the **lever** weighs the two kinds against each other. Their noise differs by data set (the camera's range,
  the arm's accuracy), so by default it is estimated from the fit itself (variance components: refit with the
  lever set to the ratio of the centre residuals' RMS to the whitened rotation residuals', ``LEVER_ROUNDS``
  times from ``LEVER_MM``), i.e. each kind weighted by its own observed spread. Measured (5-fold, fold seeds
  0..2) against the fixed 300 mm: twin seed 3 held-out rotation mean / max 0.248 / 0.710 -> 0.227 / 0.608 deg;
  Doosan and twin seed 7 within 1-2 % on every figure (docs/any-arm.md);
- **flange sag** ``S_a``: a real arm's flange droops under the tool and camera by an amount that grows with
  its horizontal reach ``r`` (joint compliance under the load's moment): the reported flange *position* is
  rotated by ``c_a * r`` about the horizontal axis perpendicular to the reach, through the point
  ``(0, 0, h_a)`` on the base's z axis (the shoulder); its orientation is kept as reported. Two numbers per
  arm (``c_a`` rad/m, ``h_a`` m); eye-in-hand only (eye-to-hand's inverted poses have no such meaning).
  Rotating the orientation too was measured and is worse on real data (Doosan, 5-fold, seeds 0..2: held-out
  centre max 2.13 mm and rotation max 1.135 deg, against 1.91 mm and 1.117 deg with the position alone).

Scored like every solver (:func:`darp.calibration.anyarm.heldout_consistency`). On the real Doosan A0509 +
D435 pairs (31 captures, 5-fold, fold seeds 0..2) it lowers the held-out board-centre mean by about a fifth
against OpenCV's best method, with the held-out rotation no worse (docs/any-arm.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import cast

import numpy as np

from darp.calibration import handeye
from darp.calibration.geometry import delta, log_delta
from darp.calibration.model import ChainParams, Observations
from darp.errors import CalibrationError
from darp.geometry.transforms import rotvec_to_rotation
from darp.kinematics.transforms import invert_transform

LEVER_MM = 300.0  # mm of residual per radian of (whitened) board rotation: the start of its estimate
LEVER_ROUNDS = 3  # re-estimations of the lever from the residuals' spreads
BETA = 0.9  # share of PnP's rotation covariance in the rotation weight (the rest: an isotropic floor)
BETAS = (0.0, 0.5, 0.9, 0.99)  # the shares tried by default; the one whose noise model explains the fit best wins


@dataclass
class SagParams(ChainParams):
    """:class:`ChainParams` with each arm's flange sag ``(c rad/m, h m)`` (absent: none)."""

    sag: dict[str, np.ndarray] = field(default_factory=dict)

    def copy(self) -> SagParams:
        base = ChainParams.copy(self)
        return SagParams(**{f: getattr(base, f) for f in ("arms", "T_ref_base", "T_wrist_cam", "dq", "T_ref_board",
                                                          "kin")}, sag={a: v.copy() for a, v in self.sag.items()})


def sag_flange(F: np.ndarray, sag: np.ndarray | None) -> np.ndarray:
    """Flange poses (n, 4, 4) corrected by a sag ``(c, h)``: positions rotated by ``c * reach`` about the
    horizontal axis perpendicular to the reach, through ``(0, 0, h)``; orientations kept."""
    if sag is None or not np.any(sag):
        return F
    c, h = float(sag[0]), float(sag[1])
    F = np.array(F, np.float64)
    p = F[:, :3, 3]
    r = np.hypot(p[:, 0], p[:, 1])
    axis = np.stack([-p[:, 1], p[:, 0], np.zeros_like(r)], 1) / np.maximum(r, 1e-9)[:, None]
    R = rotvec_to_rotation(axis * (c * r)[:, None])
    pivot = np.array([0.0, 0.0, h])
    F[:, :3, 3] = np.einsum("nij,nj->ni", R, p - pivot) + pivot
    return F


def corrected_observations(params: ChainParams, obs: Observations) -> Observations:
    """``obs`` with each arm's flange poses corrected by ``params``' sag (itself when it has none), so that
    darp's plain residuals (corner errors, reprojection) see the same flange poses as the refinement."""
    if not isinstance(params, SagParams) or not params.sag or obs.T_base_flange is None:
        return obs
    F = np.array(obs.T_base_flange)
    for a, arm in enumerate(obs.arms):
        sel = obs.arm_index == a
        if np.any(sel) and arm in params.sag:
            F[sel] = sag_flange(F[sel], params.sag[arm])
    return replace(obs, T_base_flange=F)


def pnp_rotation_covariance(K: np.ndarray, P_board: np.ndarray, T_cam_board: np.ndarray) -> np.ndarray:
    """3x3 covariance of a board pose's rotation (board frame, right perturbation) from its corners' pixels
    with unit isotropic noise: the rotation block of ``(J^T J)^-1``."""
    def project(xi: np.ndarray) -> np.ndarray:
        T = T_cam_board @ delta(xi)
        Pc = P_board @ T[:3, :3].T + T[:3, 3]
        return cast(np.ndarray, ((Pc[:, :2] / Pc[:, 2:3]) * np.diag(K)[:2] + K[:2, 2]).ravel())

    J = np.empty((2 * len(P_board), 6))
    eps = 1e-6
    for j in range(6):
        e = np.zeros(6)
        e[j] = eps
        J[:, j] = (project(e) - project(-e)) / (2 * eps)
    info = J.T @ J
    if np.linalg.cond(info) > 1e12:
        return np.eye(3) * 1e6
    return cast(np.ndarray, np.linalg.inv(info)[:3, :3])


def rotation_whitening(obs: Observations, beta: float = BETA) -> np.ndarray:
    """(M, 3, 3) per capture: ``L`` with ``L^T L`` the inverse of its rotation covariance (PnP's, normalised to a
    median trace of 3, mixed with the identity; ``beta``: PnP's share)."""
    covs = []
    for m in range(obs.n_captures):
        sel = obs.corner_capture == m
        covs.append(pnp_rotation_covariance(obs.K[m], obs.P_board[sel], obs.T_depth_board_pnp[m]))
    C = np.array(covs)
    scale = float(np.median(np.trace(C, axis1=1, axis2=2))) / 3.0
    S = beta * C / max(scale, 1e-18) + (1.0 - beta) * np.eye(3)
    return cast(np.ndarray, np.linalg.cholesky(np.linalg.inv(S)).transpose(0, 2, 1))


def refine_poses(p0: ChainParams, obs: Observations, *, sag: bool = True, beta: float | None = None,
                 lever_mm: float | None = None) -> SagParams:
    """The module's refinement from ``p0`` (board, other bases, hand-eyes and, with ``sag``, the sag terms);
    ``beta``, ``lever_mm``: fixed values (default: each estimated from the residuals, see the module)."""
    from scipy.optimize import least_squares

    from darp.calibration.refine import Layout

    if obs.T_base_flange is None:
        raise CalibrationError("the any-arm refinement needs measured flange poses")
    layout = Layout(p0.arms, {a: np.zeros(6, bool) for a in p0.arms})
    n0, n_arms = layout.size, len(obs.arms)
    centre = np.append(np.unique(obs.P_board, axis=0).mean(axis=0), 1.0)
    F, B = np.asarray(obs.T_base_flange), obs.T_depth_board_pnp
    sels = [obs.arm_index == a for a in range(n_arms)]

    def unpack(x: np.ndarray) -> SagParams:
        p = layout.unpack(x[:n0], p0)
        s = {arm: x[n0 + 2 * a:n0 + 2 * a + 2].copy() for a, arm in enumerate(obs.arms)} if sag else {}
        return SagParams(p.arms, p.T_ref_base, p.T_wrist_cam, p.dq, p.T_ref_board, p.kin, s)

    def fun(x: np.ndarray, lever: float, L: np.ndarray) -> np.ndarray:
        p = unpack(x)
        T = np.empty_like(B)
        for a, arm in enumerate(obs.arms):
            Fa = sag_flange(F[sels[a]], p.sag.get(arm))
            T[sels[a]] = p.T_ref_base[arm] @ Fa @ p.T_wrist_cam[arm] @ B[sels[a]]
        d = 1e3 * ((T @ centre)[:, :3] - (p.T_ref_board @ centre)[:3])
        r = lever * np.einsum("nij,nj->ni", L, log_delta(invert_transform(p.T_ref_board) @ T)[:, :3])
        return np.concatenate([d.ravel(), r.ravel()])

    x0 = np.zeros(n0 + (2 * n_arms if sag else 0))
    if sag:  # the pivot starts at the median flange height
        x0[n0 + 1::2] = [float(np.median(F[s][:, 2, 3])) for s in sels]
    best: tuple[float, np.ndarray] | None = None
    for b in BETAS if beta is None else (float(beta),):
        L = rotation_whitening(obs, b)
        lever = LEVER_MM if lever_mm is None else float(lever_mm)
        x = least_squares(fun, x0, method="lm", args=(lever, L)).x
        for _ in range(LEVER_ROUNDS if lever_mm is None else 0):
            res = fun(x, lever, L).reshape(2, -1)
            lever *= float(np.sqrt(np.sum(res[0] ** 2) / max(float(np.sum(res[1] ** 2)), 1e-18)))
            x = least_squares(fun, x, method="lm", args=(lever, L)).x
        nll = rotation_nll(fun(x, lever, L).reshape(2, -1)[1] / lever, L)
        if best is None or nll < best[0]:
            best = (nll, x)
    assert best is not None
    return unpack(best[1])


def rotation_nll(whitened: np.ndarray, L: np.ndarray) -> float:
    """Twice the Gaussian negative log-likelihood of whitened rotation residuals (3n) under the covariances
    ``(L^T L)^-1`` times a common variance (profiled out): how well a rotation noise model explains them."""
    s2 = max(float(np.mean(whitened ** 2)), 1e-30)
    return float(whitened.size * np.log(s2) - 2.0 * np.sum(np.log(np.abs(np.diagonal(L, axis1=1, axis2=2)))))


def anyarm_solver(obs: Observations, *, sag: bool = True) -> SagParams:
    """darp's any-arm hand-eye: the best OpenCV method starts it (by reprojection), :func:`refine_poses` ends it."""
    est = {a: handeye.opencv_hand_eye(obs, a) for a in obs.arms}
    start = handeye.chain_from_estimates({a: handeye.best(est[a]) for a in obs.arms}, obs.arms)
    return refine_poses(start, obs, sag=sag)


def anyarm_solver_no_sag(obs: Observations) -> SagParams:
    """:func:`anyarm_solver` without the sag term (eye-to-hand)."""
    return anyarm_solver(obs, sag=False)


__all__ = ["BETA", "BETAS", "LEVER_MM", "LEVER_ROUNDS", "SagParams", "anyarm_solver", "anyarm_solver_no_sag",
           "corrected_observations", "pnp_rotation_covariance", "refine_poses", "rotation_nll", "rotation_whitening",
           "sag_flange"]
