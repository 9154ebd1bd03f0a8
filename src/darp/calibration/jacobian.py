"""Analytic Jacobian of the corner reprojection residuals (the refinement's hot loop).

A corner P of capture i is seen at ``P_s = S_i X^-1 F(q_i + dq)^-1 B^-1 W P`` (stream frame) with
``S`` = T_stream_depth, ``X`` = hand-eye, ``F`` = forward kinematics, ``B`` = base in the reference
frame, ``W`` = board in the reference frame. Each pose is a right perturbation ``T0 @ delta(w, t)`` of
its start value; with ``R(w)`` its rotation and ``Jr(w)`` the right Jacobian of SO(3):

- board (appears as is):     dP_s/dw = -R_{A W0} R(w) [P]x Jr(w),        dP_s/dt = R_{A W0}
- base, hand-eye (inverted): dP_s/dw =  R_N [V]x Jr(w),                   dP_s/dt = -R_N R(w)^T
  where V is the point in the perturbed frame and N the rotation of the chain before it;
- joint offset j (axis z_j through p_j in the base frame): dP_s/ddq_j = -R_{S X^-1 F^-1} (z_j x (V_base - p_j)).
- richer model (:mod:`darp.kinematics.kinematic_model`): an origin offset of joint j along its parent
  link's axis e translates the downstream chain by ``R_j e``; a tilt of joint j's axis about e turns it
  by ``(R_j - R_{j+1}) e`` about p_j (first order; exact at zero tilt); a compliance moves link angle j
  by ``tau_j(q)`` (the joint column times the gravity torque); a backlash moves it by ``-d_j`` (the joint
  column times minus the capture's move direction; the sag's change with it, ~1e-3 of it, is neglected).

Then the pinhole derivative ``du/dP = [fx/Z, 0, -fx X/Z^2]`` (and v alike), divided by the pixel noise.
Exact at any parameter value, so the solver's steps are Gauss-Newton steps; checked against central
differences in the tests.
"""

from __future__ import annotations

from typing import cast

import numpy as np

from darp.calibration.model import ChainParams, Observations
from darp.geometry.transforms import skew
from darp.kinematics import z1
from darp.kinematics.kinematic_model import SAG_JOINTS, backlash_angles, gravity_torques, links_params
from darp.kinematics.transforms import invert_transform, rotvec_to_rotation


def right_jacobian(w: np.ndarray) -> np.ndarray:
    """Right Jacobian of SO(3) at rotation vector ``w`` (3,): R(w + dw) = R(w) Exp(Jr dw)."""
    theta = float(np.linalg.norm(w))
    K = skew(np.asarray(w, float))
    if theta < 1e-6:
        return cast(np.ndarray, np.eye(3) - 0.5 * K + K @ K / 6.0)
    return cast(np.ndarray,
                np.eye(3) - (1 - np.cos(theta)) / theta**2 * K + (theta - np.sin(theta)) / theta**3 * (K @ K))


def residuals_and_jacobian(x: np.ndarray, layout: object, p0: ChainParams, obs: Observations, sigma_px: float,
                           wrist_frame: str = "flange") -> tuple[np.ndarray, np.ndarray]:
    """Normalised reprojection residuals (2C,) and their Jacobian (2C, n) w.r.t. the layout's vector."""
    p = layout.unpack(x, p0)  # type: ignore[attr-defined]
    sl = layout.slices  # type: ignore[attr-defined]
    C = len(obs.uv)
    ci = obs.corner_capture
    # Per capture: F (at q + dq), joint axes and points, and the chain pieces.
    M = obs.n_captures
    F = np.empty((M, 4, 4))
    links = np.empty((M, 7, 4, 4))
    B = np.empty((M, 4, 4))
    X = np.empty((M, 4, 4))
    axes_child = np.broadcast_to(z1.JOINT_AXES, (M, 6, 3)).copy()  # joint axes in their child link
    tau = np.zeros((M, 6))  # gravity torques (richer model only)
    move_dir = obs.move_dir if obs.move_dir is not None else np.zeros((M, 6))
    tool = np.eye(4)
    tool[0, 3] = z1.frame_offset_m(wrist_frame)
    free_kin: dict[str, np.ndarray] = getattr(layout, "free_kin", {})
    for a, arm in enumerate(obs.arms):
        sel = obs.arm_index == a
        if np.any(sel):
            if obs.T_base_flange is not None:  # measured flange poses (any arm): no joint offsets
                F[sel] = obs.T_base_flange[sel]
            elif arm in p.kin:  # the richer model: perturbed origins, tilted axes, compliance
                Q = backlash_angles(obs.q_rad[sel] + p.dq[arm], p.kin[arm], move_dir[sel])
                links[sel] = links_params(Q, p.kin[arm])  # the backlash is already in Q
                F[sel] = links[sel, 6] @ tool
                axes_child[sel] = p.kin[arm].axes()
                tau[sel] = gravity_torques(Q, p.kin[arm].payload_kg)
            else:
                Q = obs.q_rad[sel] + p.dq[arm]
                F[sel] = z1.fk_batch(Q, wrist_frame)
                links[sel] = z1.link_transforms_batch(Q)
            B[sel], X[sel] = p.T_ref_base[arm], p.T_wrist_cam[arm]
    S = obs.T_stream_depth
    Xi, Fi, Bi = invert_transform(X), invert_transform(F), invert_transform(B)
    W = p.T_ref_board
    V_ref = obs.P_board @ W[:3, :3].T + W[:3, 3]  # (C, 3) corner in the reference frame
    V_base = np.einsum("cij,cj->ci", Bi[ci, :3, :3], V_ref) + Bi[ci, :3, 3]
    V_flange = np.einsum("cij,cj->ci", Fi[ci, :3, :3], V_base) + Fi[ci, :3, 3]
    V_cam = np.einsum("cij,cj->ci", Xi[ci, :3, :3], V_flange) + Xi[ci, :3, 3]
    P_s = np.einsum("cij,cj->ci", S[ci, :3, :3], V_cam) + S[ci, :3, 3]
    K = obs.K[ci]
    z = np.maximum(P_s[:, 2], 1e-6)
    fx, fy = K[:, 0, 0], K[:, 1, 1]
    uv = np.stack([fx * P_s[:, 0] / z + K[:, 0, 2], fy * P_s[:, 1] / z + K[:, 1, 2]], axis=1)
    r = ((uv - obs.uv) / sigma_px).reshape(-1)
    D = np.zeros((C, 2, 3))  # d(u, v)/dP_s
    D[:, 0, 0], D[:, 0, 2] = fx / z, -fx * P_s[:, 0] / z**2
    D[:, 1, 1], D[:, 1, 2] = fy / z, -fy * P_s[:, 1] / z**2
    D /= sigma_px
    R_S = S[:, :3, :3]
    R_SX = R_S @ Xi[:, :3, :3]
    R_SXF = R_SX @ Fi[:, :3, :3]
    R_A = R_SXF @ Bi[:, :3, :3]  # rotation of the chain reference -> stream
    J = np.zeros((C, 2, layout.size))  # type: ignore[attr-defined]

    def put(key: str, dP: np.ndarray) -> None:  # dP: (C, 3, k)
        s = sl[key]
        J[:, :, s] = D @ dP

    w = x[sl["board"]][:3]
    Rw = rotvec_to_rotation(w)
    Pw = obs.P_board
    dW_w = -(R_A[ci] @ (p0.T_ref_board[:3, :3] @ Rw)) @ skew(Pw) @ right_jacobian(w)
    put("board", np.concatenate([dW_w, np.broadcast_to((R_A @ p0.T_ref_board[:3, :3])[ci], (C, 3, 3))], axis=2))
    for a, arm in enumerate(obs.arms):
        mine = obs.arm_index[ci] == a
        if not np.any(mine):
            continue
        c = ci[mine]
        if f"base:{arm}" in sl:
            w = x[sl[f"base:{arm}"]][:3]
            Rt = rotvec_to_rotation(w).T
            N = R_SXF[c]
            blk = np.zeros((C, 3, 6))
            blk[mine, :, :3] = N @ skew(V_base[mine]) @ right_jacobian(w)
            blk[mine, :, 3:] = -N @ Rt
            put(f"base:{arm}", blk)
        w = x[sl[f"handeye:{arm}"]][:3]
        Rt = rotvec_to_rotation(w).T
        blk = np.zeros((C, 3, 6))
        blk[mine, :, :3] = R_S[c] @ skew(V_cam[mine]) @ right_jacobian(w)
        blk[mine, :, 3:] = -R_S[c] @ Rt
        put(f"handeye:{arm}", blk)
        free = np.flatnonzero(layout.free_joints[arm])  # type: ignore[attr-defined]

        def joint_column(j: int, c: np.ndarray, mine: np.ndarray) -> np.ndarray:
            """d P_s / d(link angle j) of this arm's corners (n, 3)."""
            axis = np.einsum("cij,cj->ci", links[c, j + 1, :3, :3], axes_child[c, j])
            point = links[c, j + 1, :3, 3]
            return cast(np.ndarray, -np.einsum("cij,cj->ci", R_SXF[c], np.cross(axis, V_base[mine] - point)))

        if free.size:
            blk = np.zeros((C, 3, free.size))
            for k, jf in enumerate(free):
                blk[mine, :, k] = joint_column(int(jf), c, mine)
            put(f"dq:{arm}", blk)
        kin_free = np.flatnonzero(free_kin.get(arm, np.zeros(0, bool)))
        if kin_free.size:
            blk = np.zeros((C, 3, kin_free.size))
            for k, nk in enumerate(kin_free):
                n = int(nk)
                if n < 18:  # origin of joint j along parent axis e: the downstream chain translates by R_j e
                    j, e = divmod(n, 3)
                    blk[mine, :, k] = -np.einsum("cij,cj->ci", R_SXF[c], links[c, j, :3, e])
                elif n < 36:  # tilt of joint j about e: the downstream chain turns by (R_j - R_j+1) e about p_j
                    j, e = divmod(n - 18, 3)
                    omega = links[c, j, :3, e] - links[c, j + 1, :3, e]
                    point = links[c, j + 1, :3, 3]
                    blk[mine, :, k] = -np.einsum("cij,cj->ci", R_SXF[c], np.cross(omega, V_base[mine] - point))
                elif n < 39:  # compliance of joint j: its link angle moves by tau_j(q)
                    j = SAG_JOINTS[n - 36]
                    blk[mine, :, k] = joint_column(j, c, mine) * tau[c, j][:, None]
                else:  # backlash of joint j: its link angle moves by -d_j (sag's change with it neglected)
                    j = n - 39
                    blk[mine, :, k] = -joint_column(j, c, mine) * move_dir[c, j][:, None]
            put(f"kin:{arm}", blk)
    return r, J.reshape(2 * C, -1)


__all__ = ["residuals_and_jacobian", "right_jacobian"]
