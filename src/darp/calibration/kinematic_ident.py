"""Which parameters of the richer kinematic model the captures can determine (identifiability).

The candidates of a model (:data:`MODEL_CANDIDATES`) are each arm's joint origin offsets (18), the two
tilt components of each joint axis across the axis (12; a tilt about the axis itself changes nothing)
and, with compliance, one compliance per gravity-loaded joint (joints 2-4), and with backlash one half dead band
per joint (only when the captures record their move directions; else "not estimated"). The Jacobian of the
residuals (noise units) is computed with every candidate free, its columns are normalised and
projected onto the orthogonal complement of everything the paper's model estimates anyway (board,
bases, hand-eyes, identifiable joint zeros). Then, greedily (a QR with column pivoting that may skip):

1. the candidate with the largest *unique fraction* ``rho`` (the norm of its projection onto the
   complement of everything chosen so far) is taken next;
2. when ``rho < rho_min`` the candidate and all the rest are **redundant**: other parameters imitate
   them (reported with the three largest imitators, e.g. joint 1's origin with the base, joint 6's with
   the hand-eye, an origin offset along a joint axis with the next origin);
3. otherwise its data-only standard deviation (conditional on the ones chosen before) is
   ``sigma_eff / (|column| rho)``, with the pixel noise inflated by ``sqrt(corners per capture)``
   when ``correlated`` (a capture's corners share its joint reading errors, so a capture, not a corner,
   is the independent unit); when that exceeds ``max_std_fraction`` of the parameter's prior
   (vendor tolerance, :data:`darp.calibration.refine.KIN_PRIOR_STD`) the data add little to the prior
   and the candidate is **poorly determined** and fixed at 0; else it is **estimated**.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from darp.calibration.jacobian import residuals_and_jacobian
from darp.calibration.model import ChainParams, Observations
from darp.calibration.refine import KIN_PRIOR_STD, Layout, imitators
from darp.errors import CalibrationError
from darp.kinematics import z1
from darp.kinematics.kinematic_model import N_PARAMS, PARAM_NAMES, SAG_JOINTS

MODELS = ("paper", "kinematic", "kinematic+compliance", "kinematic+compliance+backlash")
BACKLASH_MODELS = ("kinematic+compliance+backlash",)
NO_DIRECTION = ("not estimated: the captures record no move direction (extra.move_direction; older or real "
                "capture files), so the link's side of the dead band is unknown")


def _candidates(model: str) -> np.ndarray:
    mask = np.zeros(N_PARAMS, bool)
    if model == "paper":
        return mask
    mask[:18] = True
    for j in range(6):
        for e in range(3):
            mask[18 + 3 * j + e] = e != z1.JOINT_AXIS_INDEX[j]  # no tilt about the axis itself
    if model in ("kinematic+compliance", *BACKLASH_MODELS):
        mask[36:39] = True
    if model in BACKLASH_MODELS:
        mask[39:45] = True
    if model not in MODELS:
        raise CalibrationError(f"unknown calibration model {model!r} (choose from {', '.join(MODELS)})")
    return mask


MODEL_CANDIDATES: dict[str, np.ndarray] = {m: _candidates(m) for m in MODELS}


@dataclass(frozen=True)
class KinIdentSettings:
    """Thresholds of the kinematic identifiability analysis."""

    rho_min: float = 0.02  # unique fraction below this: redundant with other parameters
    max_std_fraction: float = 0.5  # data-only std above this fraction of the prior: poorly determined
    correlated: bool = False  # inflate the noise by sqrt(corners per capture) (conservative; fewer estimated)


@dataclass
class KinIdentifiability:
    """The identifiability table of the richer model, per arm and parameter."""

    model: str
    free: dict[str, np.ndarray]  # arm -> bool (N_PARAMS,) estimated
    table: dict[str, list[dict[str, Any]]] = field(default_factory=dict)  # arm -> one row per parameter

    def to_dict(self) -> dict[str, Any]:
        return {"model": self.model, "table": self.table,
                "n_estimated": {a: int(np.count_nonzero(v)) for a, v in self.free.items()}}


def analyse_kinematics(p0: ChainParams, obs: Observations, free_joints: dict[str, np.ndarray], model: str,
                       sigma_px: float, settings: KinIdentSettings | None = None) -> KinIdentifiability:
    """The identifiability table (module doc) of ``model``'s candidates at the parameters ``p0``."""
    s = settings or KinIdentSettings()
    cand = (MODEL_CANDIDATES[model] if model in MODEL_CANDIDATES else _candidates(model)).copy()
    no_direction = model in BACKLASH_MODELS and obs.move_dir is None
    if no_direction:  # backlash needs each capture's move direction: not a candidate without it
        cand[39:45] = False
    arms = p0.arms
    free_out = {a: np.zeros(N_PARAMS, bool) for a in arms}
    table: dict[str, list[dict[str, Any]]] = {a: [] for a in arms}
    if not cand.any():
        return KinIdentifiability(model, free_out, table)
    layout = Layout(arms, {a: np.asarray(free_joints[a], bool) for a in arms}, free_kin={a: cand.copy() for a in arms})
    _, J = residuals_and_jacobian(np.zeros(layout.size), layout, p0, obs, sigma_px)
    norms = np.linalg.norm(J, axis=0)
    Jn = J / np.where(norms > 0, norms, 1.0)
    kin_cols = layout.kin_columns()
    forced = np.setdiff1d(np.arange(layout.size), kin_cols)
    U, sv, _ = np.linalg.svd(Jn[:, forced], full_matrices=False)
    U = U[:, sv > 1e-10 * sv[0]]
    R = Jn[:, kin_cols] - U @ (U.T @ Jn[:, kin_cols])
    inflation = float(np.sqrt(len(obs.uv) / max(obs.n_captures, 1))) if s.correlated else 1.0
    # column -> (arm, parameter index)
    owner: list[tuple[str, int]] = []
    for a in arms:
        owner += [(a, int(k)) for k in np.flatnonzero(cand)]
    status: dict[int, dict[str, Any]] = {}
    remaining = list(range(len(kin_cols)))
    chosen: list[int] = []
    while remaining:
        rho = np.linalg.norm(R[:, remaining], axis=0)
        best = int(np.argmax(rho))
        col = remaining[best]
        a, k = owner[col]
        if rho[best] < s.rho_min:
            break
        remaining.pop(best)
        std = inflation / (norms[kin_cols[col]] * rho[best]) if norms[kin_cols[col]] > 0 else np.inf
        row = {"rho": float(rho[best]), "std_data": float(std), "prior_std": float(KIN_PRIOR_STD[k])}
        if std > s.max_std_fraction * KIN_PRIOR_STD[k]:
            status[col] = {**row, "status": "poorly determined",
                           "reason": f"data-only std {std / KIN_PRIOR_STD[k]:.2f} x the prior"}
            continue
        status[col] = {**row, "status": "estimated"}
        chosen.append(col)
        q = R[:, col] / rho[best]
        R = R - np.outer(q, q @ R)
    basis_cols = np.concatenate([forced, kin_cols[chosen]]).astype(int)
    for col in remaining:
        a, k = owner[col]
        target = Jn[:, kin_cols[col]]
        coef = np.linalg.lstsq(Jn[:, basis_cols], target, rcond=1e-10)[0]
        unique = float(np.linalg.norm(target - Jn[:, basis_cols] @ coef))
        status[col] = {"rho": unique, "std_data": None, "prior_std": float(KIN_PRIOR_STD[k]), "status": "redundant",
                       "reason": "imitated by " + (", ".join(imitators(coef, [layout.names[i] for i in basis_cols]))
                                                   or "a combination of the other parameters")}
    for col, (a, k) in enumerate(owner):
        if status[col]["status"] == "estimated":
            free_out[a][k] = True
    for a in arms:
        cols = {k: c for c, (arm, k) in enumerate(owner) if arm == a}
        for k, name in enumerate(PARAM_NAMES):
            if k in cols:
                table[a].append({"parameter": name, **status[cols[k]]})
            elif (model == "kinematic" and k >= 36) or (model not in BACKLASH_MODELS and k >= 39):
                continue
            elif k >= 39:
                table[a].append({"parameter": name, "status": "not estimated", "rho": 0.0, "std_data": None,
                                 "prior_std": float(KIN_PRIOR_STD[k]), "reason": NO_DIRECTION})
            else:
                j = k // 3 if k < 18 else (k - 18) // 3 if k < 36 else SAG_JOINTS[k - 36]
                table[a].append({"parameter": name, "status": "no effect", "rho": 0.0, "std_data": None,
                                 "prior_std": float(KIN_PRIOR_STD[k]),
                                 "reason": f"a tilt about joint{j + 1}'s own axis changes nothing"})
    return KinIdentifiability(model, free_out, table)


__all__ = ["BACKLASH_MODELS", "MODELS", "MODEL_CANDIDATES", "KinIdentSettings", "KinIdentifiability",
           "analyse_kinematics"]
