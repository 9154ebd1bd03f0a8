"""Joint nonlinear refinement of the whole rig from corner reprojections, with identifiability and uncertainty.

Unknowns (reference frame = the first arm's base, see :mod:`darp.calibration.model`): the hand-eye of
each arm (6 + 6), the board pose (6), the pose of every other base (6), and the joint-zero offsets of
both arms (6 + 6). Poses are perturbed on the right (``T0 @ delta(xi)``). Residuals are every corner's
reprojection error over all captures of both arms, divided by the pixel noise ``sigma_px`` and passed
through a robust loss (``soft_l1`` at 3 sigma); each free joint offset has a weak Gaussian prior
towards 0 (``prior_deg``). ``scipy.optimize.least_squares`` (trust region reflective) solves it; the
pixel noise is re-estimated from the residuals (MAD) and the problem solved again from there.

**Identifiability** is measured, not assumed: at the start, the Jacobian of the residuals with every
joint offset free is computed; each offset's column is projected onto the orthogonal complement of
all other columns (other offsets included), and ``rho = |projected| / |column|`` tells how much of the
offset's effect no other parameter can imitate. Offsets with ``rho < rho_min`` are fixed at 0. On the
Z1 this finds, for both arms, joint 1 (a rotation about the base z axis through the base origin: the
same as turning the base, or, for the reference arm, the board about that axis) and joint 6 (a
rotation about the flange x axis: the same as turning the hand-eye about it). The calibration then
holds the *effective* base yaw and hand-eye; eq. 1 is unchanged by that choice. Each fixed offset
lists (``degenerate_with``) the three parameters with the largest coefficients in its projection;
coefficients equal to :data:`DEGENERACY_DECIMALS` decimals are ties, listed in parameter order (two
parameters with the same effect share it equally, and their last bits, which change with the BLAS
kernel, must not choose the label).

**Uncertainty**: the corners of one capture share its joint-reading error, so their residuals are
not independent and ``s^2 (J^T J)^-1`` is optimistic (kept as ``covariance_iid``). The reported
covariance is the sandwich ``(J^T J)^-1 (sum_c g_c g_c^T) (J^T J)^-1`` with ``g_c = J_c^T r_c`` summed
over the residuals of capture ``c`` (clustered by capture).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np
from scipy.optimize import least_squares

from darp.calibration.geometry import delta
from darp.calibration.jacobian import residuals_and_jacobian
from darp.calibration.model import ChainParams, Observations, predict_pixels
from darp.errors import CalibrationError
from darp.kinematics.kinematic_model import PARAM_NAMES as KIN_NAMES
from darp.kinematics.kinematic_model import KinematicParams

# Prior std of the richer model's parameters ("vendor tolerances", docs/accuracy.md): joint origins 1 mm
# per axis (machined links and bearing seats), axis tilts 0.2 deg, compliance 2e-3 rad/N m (a harmonic
# drive joint of about 500 N m/rad or stiffer), backlash (half the dead band) 0.2 deg.
KIN_PRIOR_STD = np.array([1e-3] * 18 + [np.radians(0.2)] * 18 + [2e-3] * 3 + [np.radians(0.2)] * 6)

POSE_AXES = ("rx", "ry", "rz", "tx", "ty", "tz")
DEGENERACY_DECIMALS = 9  # projection coefficients (O(1)) equal to this many decimals rank as ties


@dataclass(frozen=True)
class RefineSettings:
    """Knobs of the refinement."""

    sigma_px: float = 0.25  # starting pixel noise (re-estimated)
    loss: str = "soft_l1"
    loss_scale_sigma: float = 3.0
    prior_deg: float = 1.0  # weak prior on each free joint offset (the Z1's zero bias is about +-1 deg)
    rho_min: float = 1e-3  # offsets whose unique effect is below this fraction are fixed at 0
    estimate_offsets: bool = True  # False: hand-eye, bases and board only (offsets held at 0)
    max_nfev: int = 200
    tr_solver: str = "lsmr"  # "exact" runs an SVD of the tall Jacobian per step (slow when BLAS threads contend)
    wrist_frame: str = "flange"


@dataclass
class Layout:
    """Where each unknown lives in the parameter vector."""

    arms: tuple[str, ...]
    free_joints: dict[str, np.ndarray]  # arm -> bool (6,)
    names: list[str] = field(default_factory=list)
    slices: dict[str, slice] = field(default_factory=dict)
    # arm -> bool (N_PARAMS,): the richer model's free kinematic parameters (empty: the paper's model)
    free_kin: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = 0
        blocks: list[tuple[str, tuple[str, ...]]] = [("board", POSE_AXES)]
        blocks += [(f"base:{a}", POSE_AXES) for a in self.arms[1:]]
        blocks += [(f"handeye:{a}", POSE_AXES) for a in self.arms]
        blocks += [(f"dq:{a}", tuple(f"joint{j + 1}" for j in np.flatnonzero(self.free_joints[a])))
                   for a in self.arms]
        blocks += [(f"kin:{a}", tuple(KIN_NAMES[k] for k in np.flatnonzero(self.free_kin[a])))
                   for a in self.arms if a in self.free_kin and np.any(self.free_kin[a])]
        for key, axes in blocks:
            self.slices[key] = slice(n, n + len(axes))
            self.names += [f"{key}.{ax}" for ax in axes]
            n += len(axes)

    @property
    def size(self) -> int:
        return len(self.names)

    def unpack(self, x: np.ndarray, p0: ChainParams) -> ChainParams:
        """Parameters for vector ``x`` (perturbations of ``p0``)."""
        p = p0.copy()
        p.T_ref_board = p0.T_ref_board @ delta(x[self.slices["board"]])
        for a in self.arms[1:]:
            p.T_ref_base[a] = p0.T_ref_base[a] @ delta(x[self.slices[f"base:{a}"]])
        for a in self.arms:
            p.T_wrist_cam[a] = p0.T_wrist_cam[a] @ delta(x[self.slices[f"handeye:{a}"]])
            dq = p0.dq[a].copy()
            dq[self.free_joints[a]] += x[self.slices[f"dq:{a}"]]
            p.dq[a] = dq
            if f"kin:{a}" in self.slices:
                k0 = p0.kin.get(a, KinematicParams())
                v = k0.to_vector()
                v[self.free_kin[a]] += x[self.slices[f"kin:{a}"]]
                p.kin[a] = KinematicParams.from_vector(v, k0.payload_kg)
        return p

    def kin_values(self, x: np.ndarray, p0: ChainParams) -> np.ndarray:
        """The free kinematic parameters (absolute) of every arm, concatenated."""
        out = [np.zeros(0)]
        for a in self.arms:
            if f"kin:{a}" in self.slices:
                v = p0.kin[a].to_vector() if a in p0.kin else np.zeros(len(KIN_NAMES))
                out.append(v[self.free_kin[a]] + x[self.slices[f"kin:{a}"]])
        return np.concatenate(out)

    def kin_columns(self) -> np.ndarray:
        """Indices of the free kinematic parameters in the vector."""
        return np.concatenate([np.zeros(0, int)] + [np.arange(self.slices[k].start, self.slices[k].stop)
                                                     for k in self.slices if k.startswith("kin:")]).astype(int)

    def kin_prior(self) -> np.ndarray:
        """Prior std of each free kinematic parameter (vendor tolerances, :data:`KIN_PRIOR_STD`)."""
        out = [np.zeros(0)]
        for a in self.arms:
            if f"kin:{a}" in self.slices:
                out.append(KIN_PRIOR_STD[self.free_kin[a]])
        return np.concatenate(out)

    def dq_values(self, x: np.ndarray, p0: ChainParams) -> np.ndarray:
        """The free joint offsets (absolute, rad) for the prior."""
        return np.concatenate([p0.dq[a][self.free_joints[a]] + x[self.slices[f"dq:{a}"]] for a in self.arms])


def _residuals(x: np.ndarray, layout: Layout, p0: ChainParams, obs: Observations, sigma_px: float,
               prior_rad: float, wrist_frame: str) -> np.ndarray:
    """Residuals by direct prediction (reference for the analytic Jacobian's tests)."""
    p = layout.unpack(x, p0)
    r = (predict_pixels(p, obs, wrist_frame) - obs.uv).ravel() / sigma_px
    return np.concatenate([r, layout.dq_values(x, p0) / prior_rad, layout.kin_values(x, p0) / layout.kin_prior()])


class _Problem:
    """Residuals (data + priors) and their analytic Jacobian, computed together and cached per x."""

    def __init__(self, layout: Layout, p0: ChainParams, obs: Observations, sigma_px: float, prior_rad: float,
                 wrist_frame: str) -> None:
        self.layout, self.p0, self.obs = layout, p0, obs
        self.sigma, self.prior, self.frame = sigma_px, prior_rad, wrist_frame
        self._x: np.ndarray | None = None
        self._rj: tuple[np.ndarray, np.ndarray] | None = None
        self.dq_cols = np.concatenate([np.arange(layout.slices[f"dq:{a}"].start, layout.slices[f"dq:{a}"].stop)
                                       for a in layout.arms]).astype(int)

    def _eval(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self._x is None or not np.array_equal(x, self._x):
            r, J = residuals_and_jacobian(x, self.layout, self.p0, self.obs, self.sigma, self.frame)
            r_prior = self.layout.dq_values(x, self.p0) / self.prior
            J_prior = np.zeros((len(r_prior), self.layout.size))
            J_prior[np.arange(len(r_prior)), self.dq_cols] = 1.0 / self.prior
            kin_std = self.layout.kin_prior()
            r_kin = self.layout.kin_values(x, self.p0) / kin_std
            J_kin = np.zeros((len(r_kin), self.layout.size))
            J_kin[np.arange(len(r_kin)), self.layout.kin_columns()] = 1.0 / kin_std
            self._x, self._rj = x.copy(), (np.concatenate([r, r_prior, r_kin]), np.vstack([J, J_prior, J_kin]))
        assert self._rj is not None
        return self._rj

    def fun(self, x: np.ndarray) -> np.ndarray:
        return self._eval(x)[0]

    def jac(self, x: np.ndarray) -> np.ndarray:
        return self._eval(x)[1]


def numeric_jacobian(fun: Any, x: np.ndarray, step: float = 1e-6) -> np.ndarray:
    """Central-difference Jacobian of ``fun`` at ``x``."""
    cols = []
    for k in range(len(x)):
        e = np.zeros_like(x)
        e[k] = step
        cols.append((fun(x + e) - fun(x - e)) / (2 * step))
    return np.stack(cols, axis=1)


@dataclass
class Identifiability:
    """Which joint offsets the captures can separate from every other unknown, and how well."""

    rho: dict[str, np.ndarray]  # arm -> (6,) unique fraction of each offset's effect
    predicted_std_deg: dict[str, np.ndarray]  # arm -> (6,) std if estimated (inf when not identifiable)
    identifiable: dict[str, np.ndarray]  # arm -> bool (6,)
    degenerate_with: dict[str, list[str]]  # "arm.jointN" -> names of the parameters that imitate it
    singular_values: np.ndarray  # of the projected, column-normalised offset block

    def to_dict(self) -> dict[str, Any]:
        return {"rho": {a: v.tolist() for a, v in self.rho.items()},
                "predicted_std_deg": {a: [None if not np.isfinite(s) else float(s) for s in v]
                                      for a, v in self.predicted_std_deg.items()},
                "identifiable": {a: [bool(b) for b in v] for a, v in self.identifiable.items()},
                "degenerate_with": self.degenerate_with, "singular_values": self.singular_values.tolist()}


def imitators(coef: np.ndarray, names: list[str], n: int = 3) -> list[str]:
    """The ``n`` parameters with the largest projection coefficients (above 0.05) that imitate an offset;
    magnitudes equal to :data:`DEGENERACY_DECIMALS` decimals are ties, ranked in parameter order."""
    magnitude = np.round(np.abs(coef), DEGENERACY_DECIMALS)
    top = np.lexsort((np.arange(len(coef)), -magnitude))[:n]
    return [names[k] for k in top if abs(coef[k]) > 0.05]


def analyse_identifiability(p0: ChainParams, obs: Observations, settings: RefineSettings | None = None,
                            sigma_px: float | None = None) -> Identifiability:
    """Project each joint offset's Jacobian column against all other unknowns (see the module doc)."""
    s = settings or RefineSettings()
    sigma = sigma_px or s.sigma_px
    layout = Layout(p0.arms, {a: np.ones(6, bool) for a in p0.arms})
    _, J = residuals_and_jacobian(np.zeros(layout.size), layout, p0, obs, sigma, s.wrist_frame)
    norms = np.linalg.norm(J, axis=0)
    Jn = J / np.where(norms > 0, norms, 1.0)
    G = Jn.T @ Jn  # Gram matrix of the normalised columns: every projection below is a small solve
    rho, std, ident, degenerate = {}, {}, {}, {}
    for a in p0.arms:
        sl = layout.slices[f"dq:{a}"]
        r_arm, s_arm = np.zeros(6), np.full(6, np.inf)
        for j, col in enumerate(range(sl.start, sl.stop)):
            others = np.delete(np.arange(layout.size), col)
            coef = np.linalg.lstsq(G[np.ix_(others, others)], G[others, col], rcond=1e-12)[0]
            r_arm[j] = float(np.sqrt(max(G[col, col] - G[others, col] @ coef, 0.0))) if norms[col] > 0 else 0.0
            if r_arm[j] >= s.rho_min:
                s_arm[j] = float(np.degrees(1.0 / (norms[col] * r_arm[j])))  # columns are in noise units
            else:
                degenerate[f"{a}.joint{j + 1}"] = imitators(coef, [layout.names[k] for k in others])
        rho[a], std[a], ident[a] = r_arm, s_arm, r_arm >= s.rho_min
    dq_cols = np.concatenate([np.arange(layout.slices[f"dq:{a}"].start, layout.slices[f"dq:{a}"].stop)
                              for a in p0.arms])
    oth = np.setdiff1d(np.arange(layout.size), dq_cols)
    G_oo_inv = np.linalg.pinv(G[np.ix_(oth, oth)], rcond=1e-12)
    schur = G[np.ix_(dq_cols, dq_cols)] - G[np.ix_(dq_cols, oth)] @ G_oo_inv @ G[np.ix_(oth, dq_cols)]
    sv = np.sqrt(np.clip(np.linalg.eigvalsh(0.5 * (schur + schur.T)), 0.0, None))[::-1]
    return Identifiability(rho, std, ident, degenerate, sv)


@dataclass
class RefineResult:
    """The refined parameters, their uncertainty and the fit statistics."""

    params: ChainParams
    layout: Layout
    sigma_px: float
    cost: float
    n_residuals: int
    nfev: int
    success: bool
    message: str
    covariance: np.ndarray  # (n, n) in the layout's units (rad, m), clustered by capture
    covariance_iid: np.ndarray  # (n, n) assuming independent corner errors (optimistic)
    residual_px: np.ndarray  # (C, 2) final reprojection residuals

    def std(self, key: str) -> np.ndarray:
        """Standard deviations of one block (e.g. ``"handeye:arm110"``), rad and m."""
        sl = self.layout.slices[key]
        return cast(np.ndarray, np.sqrt(np.clip(np.diag(self.covariance)[sl], 0.0, None)))

    def joint_offset_std(self, arm: str) -> np.ndarray:
        """(6,) std of each joint offset (0 where the offset was fixed)."""
        out = np.zeros(6)
        out[self.layout.free_joints[arm]] = self.std(f"dq:{arm}")
        return out


def refine(p0: ChainParams, obs: Observations, free_joints: dict[str, np.ndarray] | None = None,
           settings: RefineSettings | None = None, free_kin: dict[str, np.ndarray] | None = None) -> RefineResult:
    """Refine every unknown from ``p0`` (``free_joints``: arm -> bool (6,), default none free; ``free_kin``:
    arm -> bool (N_PARAMS,) free parameters of the richer kinematic model, default none)."""
    s = settings or RefineSettings()
    if obs.n_captures < 3:
        raise CalibrationError(f"refinement needs at least 3 usable captures, got {obs.n_captures}")
    free = {a: (np.zeros(6, bool) if free_joints is None or not s.estimate_offsets
                else np.asarray(free_joints[a], bool)) for a in p0.arms}
    layout = Layout(p0.arms, free, free_kin={a: np.asarray(v, bool) for a, v in (free_kin or {}).items()})
    prior = np.radians(s.prior_deg)
    sigma = s.sigma_px
    start = p0
    res = None
    for _ in range(2):  # solve, re-estimate the pixel noise from the residuals, solve again
        problem = _Problem(layout, start, obs, sigma, prior, s.wrist_frame)
        res = least_squares(problem.fun, np.zeros(layout.size), jac=problem.jac, method="trf", loss=s.loss,
                            f_scale=s.loss_scale_sigma, x_scale="jac", max_nfev=s.max_nfev,
                            tr_solver=s.tr_solver)
        start = layout.unpack(res.x, start)
        resid = (predict_pixels(start, obs, s.wrist_frame) - obs.uv).ravel()
        mad = 1.4826 * float(np.median(np.abs(resid - np.median(resid))))
        sigma = max(mad, 1e-3)
    assert res is not None

    final = _Problem(layout, start, obs, sigma, prior, s.wrist_frame)
    cov, cov_iid = _covariances(*final._eval(np.zeros(layout.size)), np.repeat(obs.corner_capture, 2))
    residual = predict_pixels(start, obs, s.wrist_frame) - obs.uv
    return RefineResult(params=start, layout=layout, sigma_px=sigma, cost=float(res.cost),
                        n_residuals=int(res.fun.size), nfev=int(res.nfev), success=bool(res.success),
                        message=str(res.message), covariance=cov, covariance_iid=cov_iid, residual_px=residual)


def _covariances(r: np.ndarray, J: np.ndarray, row_capture: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(capture-clustered sandwich covariance, i.i.d. covariance) from residuals r and Jacobian J.

    Corners of one capture share that capture's joint-reading error, so their residuals are
    correlated; the clustered ("sandwich") estimate sums the score per capture before squaring,
    which keeps the reported uncertainty honest when encoder noise, not pixel noise, dominates.
    """
    m, n = J.shape
    bread = np.linalg.pinv(J.T @ J)
    cov_iid = bread * float(r @ r) / max(m - n, 1)
    clusters = np.concatenate([row_capture, row_capture.max(initial=-1) + 1 + np.arange(m - len(row_capture))])
    g = J * r[:, None]
    scores = np.zeros((clusters.max() + 1, n))
    np.add.at(scores, clusters, g)
    k = scores.shape[0]
    meat = scores.T @ scores * (k / max(k - 1, 1))
    return bread @ meat @ bread, cov_iid


__all__ = ["Identifiability", "Layout", "RefineResult", "RefineSettings", "analyse_identifiability", "imitators",
           "numeric_jacobian", "refine"]
