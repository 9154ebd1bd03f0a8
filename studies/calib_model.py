#!/usr/bin/env python3
"""The richer calibration model (issue 16 item 1) on a capture folder: held-out error per model, and
planned vs random extra captures.

**Models** (``--models``): each is solved on all captures and evaluated by the solve's own k-fold
held-out board consistency (the median 3-D corner error, mm, what ``darp calib solve`` reports), with
the fit's reprojection RMS, the number of kinematic parameters estimated, and, when the folder is a
twin capture set (``truth/settings.yaml``), the estimated compliance and geometric parameters against
the twin's true draw (the geometric ones are *effective* values: redundant parameters are absorbed
by the hand-eye, bases and neighbours, so only compliance compares one to one).

**Plan** (``--plan N``): the captures are split per arm (seeded) into a fixed test set
(``--test`` per arm), a base set (``--base`` per arm) and a pool; the base set is solved with the
richer model, then N pool captures per arm are added either by the greedy D-optimal selection
(:mod:`darp.calibration.plan_model`, which sees only the pool's joint configurations) or at random
(``--random-draws`` draws), and each calibration is scored on the test set (median 3-D corner error).

    .venv/bin/python studies/calib_model.py CAPTURES [--models paper,kinematic,kinematic+compliance+backlash]
        [--plan 6 --base 8 --test 12 --random-draws 3] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from darp.calibration.captures import read_captures
from darp.calibration.detect import DetectionSettings, detect_captures
from darp.calibration.evaluate import corner_errors, kfold_heldout
from darp.calibration.model import Observations, build_observations, reprojection_errors
from darp.calibration.plan_model import select_extra_poses
from darp.calibration.solve import calibrate_observations
from darp.kinematics.kinematic_model import PARAM_NAMES


def _true_kinematics(folder: Path) -> dict[str, Any] | None:
    path = folder / "truth" / "settings.yaml"
    if not path.is_file():
        return None
    from darp.twin.arm_errors import KinematicErrors
    from darp.twin.settings import TwinSettings

    s = TwinSettings.load(path)
    out: dict[str, Any] = {"compliance": (1.0 / s.arm_errors.joint_stiffness_nm_per_rad
                                          if s.arm_errors.joint_stiffness_nm_per_rad > 0 else 0.0)}
    for arm in ("arm110", "arm111"):
        kin = KinematicErrors.draw(s.arm_errors, s.rng(f"kinematics:{arm}"))
        out[arm] = None if kin is None else np.concatenate([kin.origin_m.ravel(), kin.axis_tilt_rad.ravel()])
    return out


def models_table(obs: Observations, models: list[str], folds: int, truth: dict[str, Any] | None) -> dict[str, Any]:
    rows: dict[str, Any] = {}
    for model in models:
        tick = time.perf_counter()
        core = calibrate_observations(obs, model=model)
        free = core.identifiability.identifiable if core.identifiability else None
        fk = core.kin_ident.free if core.kin_ident else None
        held = kfold_heldout(obs, lambda o, m=model, f=free, k=fk: calibrate_observations(  # type: ignore[misc]
            o, free_joints=f, model=m, free_kin=k).params, folds, 0)
        err = reprojection_errors(core.params, obs)
        arm_of = obs.arm_index[obs.corner_capture]
        row: dict[str, Any] = {"time_s": time.perf_counter() - tick, "arms": {}}
        for a, arm in enumerate(obs.arms):
            entry: dict[str, Any] = {
                "heldout_median_mm": float(np.median(held["per_arm"][arm]["corner_3d_mm"])),
                "heldout_p90_mm": float(np.percentile(held["per_arm"][arm]["corner_3d_mm"], 90)),
                "fit_rms_px": float(np.sqrt(np.mean(err[arm_of == a] ** 2))),
                "n_kinematic": 0 if fk is None else int(np.count_nonzero(fk[arm]))}
            if arm in core.params.kin:
                kin = core.params.kin[arm]
                entry["compliance_rad_per_nm"] = kin.compliance_rad_per_nm[1:4].tolist()
                if truth is not None and truth.get(arm) is not None and fk is not None:
                    v = kin.to_vector()
                    entry["vs_truth"] = {PARAM_NAMES[k]: [float(v[k]), float(truth[arm][k])]
                                         for k in np.flatnonzero(fk[arm]) if k < 36}
            row["arms"][arm] = entry
        rows[model] = row
        texts = []
        for arm, e in row["arms"].items():
            comp = (f", c2-4 {np.round(np.array(e['compliance_rad_per_nm']) * 1e3, 2)} mrad/Nm"
                    if "compliance_rad_per_nm" in e else "")
            texts.append(f"{arm}: held-out {e['heldout_median_mm']:.3f} mm (p90 {e['heldout_p90_mm']:.2f}), "
                         f"fit {e['fit_rms_px']:.2f} px, {e['n_kinematic']} kin{comp}")
        print(f"{model:22s} " + "  ".join(texts) + f"  [{row['time_s']:.0f} s]", flush=True)
    if truth is not None:
        print(f"true compliance (joints 2-4): {truth['compliance'] * 1e3:.2f} mrad/N m")
    return rows


def plan_experiment(obs: Observations, board: Any, n_extra: int, n_base: int, n_test: int, draws: int,
                    model: str, seed: int) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    base, test, pool = [], [], {}
    for arm in obs.arms:
        idx = rng.permutation(np.flatnonzero(obs.for_arm(arm)))
        test += list(idx[:n_test])
        base += list(idx[n_test:n_test + n_base])
        pool[arm] = idx[n_test + n_base:]
    obs_test = obs.subset(np.array(test))

    def score(extra: list[int]) -> float:
        core = calibrate_observations(obs.subset(np.array(base + extra)), model=model)
        return float(np.median(corner_errors(core.params, obs_test)["corner_3d_mm"]))

    base_core = calibrate_observations(obs.subset(np.array(base)), model=model)
    out: dict[str, Any] = {"base_only_mm": float(np.median(corner_errors(base_core.params, obs_test)["corner_3d_mm"]))}
    print(f"plan: base {n_base}/arm, test {n_test}/arm, pool {', '.join(str(len(p)) for p in pool.values())}; "
          f"base only: {out['base_only_mm']:.3f} mm", flush=True)
    assert base_core.identifiability is not None
    picks = select_extra_poses(base_core.params, obs.subset(np.array(base)), board,
                               {a: obs.q_rad[pool[a]] for a in obs.arms}, base_core.identifiability.identifiable,
                               n_extra * len(obs.arms), model, base_core.refined.sigma_px)
    planned = [int(pool[a][k]) for a, k in picks]
    out["planned_mm"] = score(planned)
    out["planned_per_arm"] = {a: sum(1 for x, _ in picks if x == a) for a in obs.arms}
    print(f"  + {n_extra * len(obs.arms)} planned {out['planned_per_arm']}: {out['planned_mm']:.3f} mm", flush=True)
    out["random_mm"] = []
    for d in range(draws):
        r = np.random.default_rng([seed, d])
        extra = [int(i) for a in obs.arms for i in r.choice(pool[a], n_extra, replace=False)]
        out["random_mm"].append(score(extra))
        print(f"  + {n_extra} random per arm (draw {d}): {out['random_mm'][-1]:.3f} mm", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("captures", type=Path)
    ap.add_argument("--models", default="paper,kinematic,kinematic+compliance,kinematic+compliance+backlash")
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument("--plan", type=int, default=0, help="extra captures per arm (0: no plan experiment)")
    ap.add_argument("--base", type=int, default=8)
    ap.add_argument("--test", type=int, default=12)
    ap.add_argument("--random-draws", type=int, default=3)
    ap.add_argument("--plan-model", default="kinematic+compliance")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    caps = read_captures(args.captures)
    obs = build_observations(detect_captures(caps, DetectionSettings()), caps.board, tuple(sorted(caps.arms)))
    print(f"{args.captures}: {obs.n_captures} captures, {len(obs.uv)} corners", flush=True)
    result: dict[str, Any] = {"captures": str(args.captures), "n_captures": obs.n_captures}
    if args.models:
        result["models"] = models_table(obs, args.models.split(","), args.folds, _true_kinematics(args.captures))
    if args.plan:
        result["plan"] = plan_experiment(obs, caps.board, args.plan, args.base, args.test, args.random_draws,
                                         args.plan_model, args.seed)
    if args.json:
        args.json.write_text(json.dumps(result, indent=1, default=float), encoding="utf-8")


if __name__ == "__main__":
    main()
