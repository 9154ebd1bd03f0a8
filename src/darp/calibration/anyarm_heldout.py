"""Held-out scores of an any-arm hand-eye that other tools can reproduce: the split and the board consistency.

**The fold split** (:func:`fold_split`): each arm's captures, in the natural order of their ids, shuffled with
``numpy.random.default_rng([seed, 0xF01D]).permutation`` and dealt round-robin into ``k`` folds (darp's
calibration split, :func:`darp.calibration.evaluate.fold_assignment`); the report writes the fold of every
capture (``heldout.fold_of``), and ``--folds-file FILE`` gives one instead: lines ``capture_id fold`` (or
``capture_id,fold``; a JSON ``{id: fold}`` works too; ``#`` comments), every used capture named once.

**Board consistency**: each withheld capture places the board in the reference frame by itself (``F_i X
T_cam_board_i``, with the calibration made without its fold); against the calibration's own board it gives

- the distance of the board's **centre** (mm) and of its **corner** (the board frame's origin, where OpenCV's
  ``estimatePoseCharucoBoard`` / ``solvePnP`` put the board's pose, and where most tools score it), and
- the rotation angle (deg);

each as mean and max over the withheld captures.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from darp.calibration.anyarm_refine import corrected_observations
from darp.calibration.evaluate import corner_errors, fold_assignment, summarise
from darp.calibration.model import ChainParams, Observations, flange_poses
from darp.errors import FormatError
from darp.kinematics.transforms import pose_error

Solver = Callable[[Observations], ChainParams]


def read_folds_file(path: str | Path) -> dict[str, int]:
    """``{capture id: fold}`` from a folds file (module docstring)."""
    from darp.formats.pairing import frame_id

    p = Path(path)
    from darp.formats.text import read_utf8_text

    text = read_utf8_text(p, "a folds file")
    out: dict[str, int] = {}
    try:
        if text.lstrip().startswith("{"):
            items = [(str(k), int(v)) for k, v in json.loads(text).items()]
        else:
            items = []
            for n, line in enumerate(text.splitlines()):
                s = line.split("#")[0].replace(",", " ").split()
                if not s or (n == 0 and not s[-1].lstrip("-").isdigit()):
                    continue
                if len(s) != 2 or not s[1].lstrip("-").isdigit():
                    raise FormatError(f"line {n + 1}: expected 'capture_id fold'", p)
                items.append((s[0], int(s[1])))
    except (ValueError, json.JSONDecodeError) as err:
        raise FormatError(f"not a folds file ({err})", p) from None
    for k, v in items:
        key = frame_id(k.split("/")[-1]) if "/" not in k else k.split("/")[0] + "/" + frame_id(k.split("/")[1])
        if key in out:
            raise FormatError(f"capture {k!r} is listed twice", p)
        out[key] = v
    return out


def fold_split(obs: Observations, k: int, seed: int = 0, folds_file: str | Path | None = None) -> np.ndarray:
    """Fold index (M,) per capture: darp's seeded split, or the folds file's (every capture must be in it)."""
    if folds_file is None:
        return fold_assignment(obs, k, seed)
    given = read_folds_file(folds_file)
    missing = [c for c in obs.capture_ids if c not in given]
    if missing:
        raise FormatError(f"capture {missing[0]!r} (and {len(missing) - 1} more) has no fold; list every capture",
                          folds_file)
    labels = sorted({given[c] for c in obs.capture_ids})
    return np.array([labels.index(given[c]) for c in obs.capture_ids])


def board_in_reference(params: ChainParams, obs: Observations) -> np.ndarray:
    """(M, 4, 4) the board placed in the reference frame by each capture alone (sag-corrected flange poses)."""
    obs = corrected_observations(params, obs)
    out = np.empty((obs.n_captures, 4, 4))
    for a, arm in enumerate(obs.arms):
        sel = obs.arm_index == a
        if np.any(sel):
            out[sel] = (params.T_ref_base[arm] @ flange_poses(obs, sel, params.dq[arm]) @ params.T_wrist_cam[arm]
                        @ obs.T_depth_board_pnp[sel])
    return out


def board_consistency(params: ChainParams, obs: Observations, centre_board: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per capture: distance (mm) of the board centre, of the board corner (origin), and rotation (deg)."""
    T = board_in_reference(params, obs)
    out = []
    for point in (np.asarray(centre_board, np.float64), np.zeros(3)):
        c = np.append(point, 1.0)
        out.append(1e3 * np.linalg.norm((T @ c)[:, :3] - (params.T_ref_board @ c)[:3], axis=1))
    _, r = pose_error(T, np.broadcast_to(params.T_ref_board, T.shape))
    return out[0], out[1], np.degrees(np.asarray(r))


def heldout_consistency(obs: Observations, solver: Solver, centre_board: np.ndarray, folds: np.ndarray
                        ) -> dict[str, Any]:
    """Held-out board consistency over a fold split (each withheld capture against the calibration made
    without its fold): ``mm`` (centre), ``corner_mm``, ``deg`` summaries and per capture."""
    n = obs.n_captures
    mm, corner, deg = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    for f in np.unique(folds):
        test = folds == f
        if np.all(test):
            continue
        params = solver(obs.subset(~test))
        mm[test], corner[test], deg[test] = board_consistency(params, obs.subset(test), centre_board)
    ok = np.isfinite(mm)
    return {"folds": int(len(np.unique(folds))), "mm": summarise(mm[ok]), "corner_mm": summarise(corner[ok]),
            "deg": summarise(deg[ok]),
            "per_capture": {c: {"mm": float(a), "corner_mm": float(b), "deg": float(d), "fold": int(f)}
                            for c, a, b, d, f in zip(obs.capture_ids, mm, corner, deg, folds, strict=True)}}


def heldout_corners(obs: Observations, solver: Solver, folds: np.ndarray) -> dict[str, dict[str, np.ndarray]]:
    """Held-out corner errors per arm (``corner_3d_mm``, ``reprojection_px`` arrays over withheld corners), with
    the solver's sag (when it has one) applied to the withheld captures' flange poses."""
    out: dict[str, dict[str, list[np.ndarray]]] = {a: {"corner_3d_mm": [], "reprojection_px": []} for a in obs.arms}
    for f in np.unique(folds):
        test = folds == f
        if np.all(test):
            continue
        params = solver(obs.subset(~test))
        sub = corrected_observations(params, obs.subset(test))
        errs = corner_errors(params, sub)
        for a, arm in enumerate(obs.arms):
            mine = sub.arm_index[sub.corner_capture] == a
            for key in out[arm]:
                out[arm][key].append(errs[key][mine])
    return {a: {k: np.concatenate(v) if v else np.zeros(0) for k, v in d.items()} for a, d in out.items()}


__all__ = ["board_consistency", "board_in_reference", "fold_split", "heldout_consistency", "heldout_corners",
           "read_folds_file"]
